"""Learning curves of an experiment: every training run's per-iteration scalars in one compact
file, ``<experiment>_curves.csv.gz``, committed with the results, so that any claim about
training (does the learner adapt, when, how the adversary moves) can be re-derived; and their
figure, ``<experiment>_curves.png``.

A run's curve is read from its CSV log (``logs/scalars``, :data:`CURVES`); a run whose log is
gone (a results directory checked out without its runs' logs) keeps its rows from the file
already there.
"""

from __future__ import annotations

import csv
import gzip
import io
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from armeta_rl.reproduce.packed import NOTHING_PACKED, Packed
from armeta_rl.reproduce.plan import Plan, finished
from armeta_rl.run_files import FileRefused, gunzip, read_file, read_text
from armeta_rl.trainers.run_dir import CSV_LOG_DIR, LOG_BYTES, write_atomically

CURVES = {
    "return_pre": "train/return_pre",
    "return_post": "train/return_post",
    "gain": "train/gain",
    "task_loss_mean": "train/task_loss_mean",
    "adversary_entropy": "adversary/entropy",
    "adversary_kl_p0": "adversary/kl_p0",
    "task_spread": "risk/spread",
    "adversary_step_kl": "adversary/step_kl",
}
"""A curve file's columns and the scalars they hold (absent scalars are left empty: the
returns and gain are meta-RL's, the adversary's entropy and KL from p0 AR methods', the spread
of the training batch's identifiers (their mean pairwise distance in the unit box; 1/3 for a
uniform batch in one dimension) MPTS's and PDTS's, the KL between p_φ before and after each
update the natural-step follower's (``risk.ar.step=natural``))."""
KEYS = ("benchmark", "run", "seed", "iteration")
"""A row's run: its benchmark, its name (``<method>[-<variant>]``, ``<method>-vs-<target>`` for
an attack run: :attr:`~armeta_rl.reproduce.plan.TrainRun.name`), seed and iteration."""
DIGITS = 6
"""Significant digits kept of every value."""
CURVE_BYTES = 2**28
"""The most a curve file is read, compressed and decompressed (256 MiB; HalfCheetah-Vel's 40
runs of 400 iterations hold 1.2 MiB)."""


def curves_path(results: Path, experiment: str) -> Path:
    """``<results>/<experiment>_curves.csv.gz``."""
    return results / f"{experiment}_curves.csv.gz"


def run_curve(run_dir: Path) -> dict[int, dict[str, float]]:
    """Iteration → the run's logged scalars of :data:`CURVES` at that iteration; empty when the
    run has no CSV log. A run whose log has no gain scalar gets return_post − return_pre."""
    rows: dict[int, dict[str, float]] = {}
    for column, name in CURVES.items():
        for iteration, value in logged_scalar(run_dir, name).items():
            rows.setdefault(iteration, {})[column] = value
    for row in rows.values():
        if "gain" not in row and {"return_pre", "return_post"} <= row.keys():
            row["gain"] = row["return_post"] - row["return_pre"]
    return rows


def logged_scalar(run_dir: Path, name: str) -> dict[int, float]:
    """Iteration → the value of scalar ``name`` (``train/gain``, say) in the run's CSV log (the
    last row of an iteration a resumed run logged twice); empty when the run has no such log."""
    try:
        text = read_text(run_dir / CSV_LOG_DIR / "scalars" / f"{name}.csv", LOG_BYTES, run_dir)
    except (OSError, FileRefused):
        return {}
    return {int(line[0]): float(line[1]) for line in csv.reader(text.splitlines())
            if len(line) == 2 and line[0].isdigit()}


def read_curves(path: Path) -> list[dict[str, Any]]:
    """The rows of a curve file (numbers parsed, empty cells and columns the file predates
    ``None``); none if it is absent. Read bounded (:data:`CURVE_BYTES`, compressed and
    decompressed) as any file of a results directory.

    Raises:
        FileRefused: the file cannot be read as a curve file (not a regular file of one link,
            larger than the bound, damaged or cut short, or a cell that is not a number).
    """
    try:
        data = gunzip(read_file(path, CURVE_BYTES), CURVE_BYTES, path)
        text = data.decode("utf-8")
        return [{key: _parse(key, row.get(key) or "") for key in (*KEYS, *CURVES)}
                for row in csv.DictReader(io.StringIO(text, newline=""))]
    except FileNotFoundError:
        return []
    except (OSError, UnicodeDecodeError, ValueError, csv.Error) as error:
        if isinstance(error, FileRefused):
            raise
        reason = error.strerror if isinstance(error, OSError) else error
        raise FileRefused(path, f"cannot be read as a curve file ({reason})") from None


def _parse(key: str, value: str) -> Any:
    if key in ("benchmark", "run"):
        return value
    if value == "":
        return None
    return int(value) if key in ("seed", "iteration") else float(value)


def collect_curves(plan: Plan, results: Path, kept: Sequence[dict[str, Any]] = (),
                   packed: Packed = NOTHING_PACKED) -> list[dict[str, Any]]:
    """One row per iteration of every finished training run of ``plan`` (attack runs included;
    a run still training is left out; a packed run is finished): from the run's log where it has
    one (at the file's precision), else its rows in ``kept`` (the experiment's file as it was)."""
    old: dict[tuple, list[dict[str, Any]]] = {}
    for row in kept:
        old.setdefault(_identity(row), []).append(row)
    rows = []
    for run in (*plan.runs, *plan.attacks):
        identity = (run.benchmark, run.name, run.seed)
        if not finished(results, run, packed):
            continue
        curve = run_curve(results / run.subdir)
        if not curve:
            rows += old.get(identity, [])
            continue
        for iteration in sorted(curve):
            rows.append({**dict(zip(KEYS, (*identity, iteration))),
                         **{column: _kept(curve[iteration].get(column)) for column in CURVES}})
    return rows


def _kept(value: float | None) -> float | None:
    """``value`` at the file's :data:`DIGITS` significant digits: a row from a log equals the
    row its file gives back, so that whatever is drawn from it is drawn alike without the log."""
    return None if value is None else float(f"{value:.{DIGITS}g}")


def _identity(row: dict[str, Any]) -> tuple:
    return row["benchmark"], row["run"], row["seed"]


def write_curves(rows: Iterable[dict[str, Any]], path: Path) -> None:
    """The rows as a gzipped CSV (no timestamp in the header: the same rows give the same
    bytes), written atomically."""
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=[*KEYS, *CURVES], restval="")
    writer.writeheader()
    for row in rows:
        writer.writerow({key: _format(row.get(key)) for key in (*KEYS, *CURVES)})
    data = gzip.compress(text.getvalue().encode(), mtime=0)
    write_atomically(path, lambda staged: staged.write_bytes(data))


def _format(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.{DIGITS}g}"
    return value


def windowed(values: Sequence[tuple[int, float]], window: int) -> list[tuple[int, float]]:
    """Means of consecutive windows of ``window`` iterations: (the window's last iteration, the
    mean of its values), for curves whose per-iteration noise hides their trend."""
    by_window: dict[int, list[float]] = {}
    for iteration, value in values:
        by_window.setdefault((iteration - 1) // window, []).append(value)
    return [(min((k + 1) * window, max(i for i, _ in values)), math.fsum(v) / len(v))
            for k, v in sorted(by_window.items())]


LATE_PARTS = 5
"""A run's late change compares the mean over the last fifth of its iterations with the mean
over the fifth before it."""


def late_parts(last: int) -> tuple[range, range]:
    """The iterations of the last 1/:data:`LATE_PARTS` of a run that ends at ``last`` and of the
    1/:data:`LATE_PARTS` before them (of 500: 401–500 and 301–400)."""
    late, before = (math.floor(last - k * last / LATE_PARTS) + 1 for k in (1, 2))
    return range(late, last + 1), range(before, late)


def late_means(rows: Sequence[dict[str, Any]],
               column: str) -> dict[tuple[str, str], list[tuple[float, float]]]:
    """(benchmark, run) → each seed's mean of ``column`` over the run's last part and over the
    part before (:func:`late_parts` of the seed's last logged iteration); a seed with no value
    of ``column`` in either part is left out."""
    by_seed: dict[tuple[str, str, int], list[tuple[int, float]]] = {}
    for row in rows:
        if row[column] is not None:
            by_seed.setdefault(_identity(row), []).append((row["iteration"], row[column]))
    means: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for (benchmark, run, _), values in by_seed.items():
        late_part, before_part = late_parts(max(iteration for iteration, _ in values))
        late = [v for i, v in values if i in late_part]
        before = [v for i, v in values if i in before_part]
        if late and before:
            means.setdefault((benchmark, run), []).append(
                (math.fsum(late) / len(late), math.fsum(before) / len(before)))
    return means


def late_changes(means: dict[tuple[str, str], list[tuple[float, float]]]
                 ) -> dict[tuple[str, str], list[float]]:
    """(benchmark, run) → each seed's late change, from its :func:`late_means`: its mean over
    the run's last part minus its mean over the part before. Whether a learner still improves
    where it was compared (or an adversary still moves)."""
    return {key: [late - before for late, before in seeds] for key, seeds in means.items()}


def late_levels(means: dict[tuple[str, str], list[tuple[float, float]]]
                ) -> dict[tuple[str, str], float]:
    """(benchmark, run) → the mean over seeds of the last part's means (:func:`late_means`): the
    level a late change (:func:`late_changes`) is a change of, whose decimals the change is
    shown with."""
    return {key: math.fsum(late for late, _ in seeds) / len(seeds)
            for key, seeds in means.items()}
