"""Aggregation of an experiment's runs: one record per (run, distribution) in ``<experiment>.csv``,
mean ± standard deviation over seeds, CVaR_α curves, and ``<experiment>.md`` laid out like the
paper's table or figure, with the paper's numbers beside ours where the paper prints them.

Over seeds, ``std`` is the sample standard deviation (n − 1; the paper's "± … (5 runs)") and
``se`` the standard error std/√n (the paper's error bars and shaded bands).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from armeta_rl.config import CONFIG_FILE
from armeta_rl.reproduce.curves import logged_scalar
from armeta_rl.reproduce.packed import NOTHING_PACKED, Packed
from armeta_rl.reproduce.plan import (
    EVAL_FILE,
    EvalJob,
    Plan,
    TrainRun,
    finished,
    finished_report,
    identity_problem,
    load_report,
)
from armeta_rl.trainers.checkpoint import checkpoint_dirs
from armeta_rl.trainers.evaluation import ReportInvalid, share_resolved
from armeta_rl.trainers.game import ITERATION_TIME
from armeta_rl.trainers.run_dir import write_text_atomically

INITIAL = "initial"
SHIFT_PREFIX = "shift/"
NUMBER_COLUMNS = ("mean", "sem", "entropy", "kl_p0", "n_tasks", "rollouts", "rollout_sd", "seed")
ADAPTATION_COLUMNS = ("before", "before_sem", "gain", "gain_sem", "improved")
"""A meta-RL section's score before adaptation and adaptation gain (its ``adaptation``,
:func:`~armeta_rl.trainers.evaluation.adaptation_gain`); empty for other benchmarks."""
QUARTER_FIELDS = ("quarter_mass", "quarter_scores")
"""A section's masses and the learner's mean scores in the four quarters of the box, as the
columns ``quarter_mass_<q>`` and ``quarter_scores_<q>`` (q = 0 … 3; sections evaluated before
they were recorded have none)."""
GOAL_COLUMNS = {"achieved": "goal_achieved", "blind": "goal_blind", "oracle": "goal_oracle",
                "gap_closed": "gap_closed", "gap_closed_sem": "gap_closed_sem"}
"""A meta-RL section's ``goal`` (the share of the goal-blind gap closed and the mean goal terms
it is made of, :func:`~armeta_rl.trainers.evaluation.goal_section`) → its columns; only where
the benchmark knows the references."""
KEPT_OUT_OF_CSV = ("per_task",)
"""Record fields the CSV leaves out: the per-task scores (in the runs' reports)."""


@dataclass(frozen=True)
class SeedSummary:
    """A quantity over seeds: mean, sample standard deviation, standard error, count."""

    mean: float
    std: float
    se: float
    n: int

    def format(self, spread: str = "std") -> str:
        """``mean ± std`` (``spread="se"``: ± the standard error; just the mean for one seed),
        both with the decimals :func:`decimals` gives the mean."""
        places = decimals(self.mean)
        if self.n < 2:
            return f"{self.mean:.{places}f}"
        return f"{self.mean:.{places}f} ± {getattr(self, spread):.{places}f}"


def decimals(value: float) -> int:
    """Decimal places to show ``value`` with: 3 as the paper writes MSEs, 1 from 10 on (returns),
    3 significant digits below 0.1 (the system-identification MSEs)."""
    size = abs(value)
    if size >= 10:
        return 1
    if size >= 0.1 or size == 0 or not math.isfinite(size):
        return 3
    return 2 - math.floor(math.log10(size))


def difference_decimals(scale: float, error: float) -> int:
    """Decimal places to show a difference between values of size ``scale`` with its ``error``:
    :func:`decimals` of the values, so that a difference of returns reads like the returns it
    compares (+5.3 ± 1.9 beside returns of −60), with more places only where the error would
    round to zero at the values' own (then to the error's first significant digit).

    Examples:
        >>> from armeta_rl.reproduce.aggregate import difference_decimals
        >>> difference_decimals(-60.2, 1.946), difference_decimals(-60.2, 0.04)
        (1, 2)
        >>> difference_decimals(2.05, 0.048)  # ratios near 2: the values' three places
        3
    """
    places = decimals(scale)
    if math.isfinite(error) and error > 0:
        places = max(places, -math.floor(math.log10(error)))
    return places


def over_seeds(values: Sequence[float]) -> SeedSummary:
    """Mean, sample std (n − 1) and standard error of ``values`` (std and se NaN for one value)."""
    n = len(values)
    if n == 0:
        raise ValueError("no values to summarize")
    mean = math.fsum(values) / n
    if n < 2:
        return SeedSummary(mean, math.nan, math.nan, n)
    std = math.sqrt(math.fsum((v - mean) ** 2 for v in values) / (n - 1))
    return SeedSummary(mean, std, std / math.sqrt(n), n)


def cvar_alpha(key: str, prefix: str = "cvar_") -> float | None:
    """α of a record's column ``cvar_<α>`` (with ``prefix="cvar_sem_"``: of ``cvar_sem_<α>``),
    ``None`` for any other column."""
    if not key.startswith(prefix):
        return None
    try:
        return float(key[len(prefix):])
    except ValueError:
        return None


def cvar_curve(record: dict[str, Any]) -> tuple[list[float], list[float]]:
    """CVaR_α of one record for α = 0 (the mean: the whole distribution is the tail) and every α
    it holds, in increasing α."""
    alphas = sorted(cvar_alpha(key) for key in record if cvar_alpha(key) is not None
                    and record[key] != "")
    return [0.0, *alphas], [record["mean"], *(record[f"cvar_{a}"] for a in alphas)]


def curve_over_seeds(records: Sequence[dict[str, Any]]) -> tuple[list[float], list[SeedSummary]]:
    """CVaR_α curves of several seeds: for each α, the mean and standard error over seeds (the
    α grid is the one all records share)."""
    curves = [cvar_curve(r) for r in records]
    alphas = sorted(set.intersection(*(set(a) for a, _ in curves)))
    return alphas, [over_seeds([dict(zip(a, v))[alpha] for a, v in curves]) for alpha in alphas]


def method_curve(records: Iterable[dict[str, Any]], benchmark: str, method: str,
                 distribution: str) -> tuple[list[float], list[SeedSummary]] | None:
    """The clean-label CVaR_α curve over seeds of ``method`` on ``benchmark`` and
    ``distribution`` (:func:`curve_over_seeds`), or ``None`` when no seed has finished."""
    chosen = select(records, benchmark=benchmark, method=method, distribution=distribution,
                    noisy=False)
    return curve_over_seeds(chosen) if chosen else None


def section_records(report: dict[str, Any], section: str, distribution: str,
                    noisy: bool) -> list[dict[str, Any]]:
    """The record of ``report[section]`` (one distribution of an ``eval.json``), if present."""
    if section not in report:
        return []
    data = report[section]
    record = {"distribution": distribution, "noisy": noisy, "metric": report["metric"]}
    record.update({key: data.get(key) for key in NUMBER_COLUMNS})
    record["task_seed"] = record.pop("seed")
    record.update({f"cvar_{float(a)}": v for a, v in data["cvar"].items()})
    record.update({f"cvar_sem_{float(a)}": v for a, v in data.get("cvar_sem", {}).items()})
    adaptation = data.get("adaptation") or {}
    record.update({key: adaptation.get(key) for key in ADAPTATION_COLUMNS})
    record.update(evidence_columns(data))
    if "machine" in report:  # reports written before it was recorded keep their CSV columns
        record["machine"] = report["machine"]
    record["per_task"] = data.get("per_task")
    return [record]


def evidence_columns(section: dict[str, Any]) -> dict[str, Any]:
    """The columns of the fields a section holds only where its evaluation recorded them: the
    KL's standard error (``kl_p0_sem``), the quarters (:data:`QUARTER_FIELDS`) and the goal
    references (:data:`GOAL_COLUMNS`); none for a section evaluated before them, so its CSV
    row keeps its columns. A share of the goal-blind gap closed whose standard error is above
    1 (:func:`~armeta_rl.trainers.evaluation.share_resolved`; a report evaluated without the
    rule may carry one) is undefined, its error with it, as
    :func:`~armeta_rl.trainers.evaluation.gap_closed` gives it."""
    columns: dict[str, Any] = {}
    if "kl_p0_sem" in section:
        columns["kl_p0_sem"] = section["kl_p0_sem"]
    for field in QUARTER_FIELDS:
        if section.get(field) is not None:
            columns.update({f"{field}_{q}": value for q, value in enumerate(section[field])})
    goal = section.get("goal")
    if goal is not None:
        columns.update({column: goal.get(key) for key, column in GOAL_COLUMNS.items()})
        if not share_resolved(goal.get("gap_closed_sem")):
            columns.update(gap_closed=None, gap_closed_sem=None)
    return columns


def run_seconds(run_dir: Path) -> float | None:
    """A finished run's wall time from its files: from its ``config.yaml`` (written as it starts)
    to its ``eval.json`` (written as it ends), interruptions of a resumed run included."""
    config = run_dir / CONFIG_FILE
    if not config.is_file():
        return None
    return (run_dir / EVAL_FILE).stat().st_mtime - config.stat().st_mtime


def logged_seconds(run_dir: Path) -> float | None:
    """A run's time training as its CSV log holds it: the sum of its iterations' logged times
    (:data:`ITERATION_TIME`), so that the pauses of a run stopped and resumed count nothing;
    ``None`` unless the log holds every iteration from the first."""
    times = logged_scalar(run_dir, ITERATION_TIME)
    if not times or sorted(times) != list(range(1, len(times) + 1)):
        return None
    return sum(times.values()) / 1000.0


def train_seconds(plan: Plan, results: Path, known: dict[str, float]) -> dict[str, float]:
    """Each finished run's wall time, by its subdirectory: :func:`logged_seconds` where the run
    has its log, else the value in ``known`` (the results directory's manifest, which keeps it
    across checkouts that carry no logs and reset file times, and forgets it when the run is to
    be trained again), else :func:`run_seconds`."""
    seconds = dict(known)
    for run in plan.runs:
        run_dir = results / run.subdir
        if not (run_dir / EVAL_FILE).is_file():
            continue
        measured = logged_seconds(run_dir)
        if measured is None and run.subdir not in seconds:
            measured = run_seconds(run_dir)
        if measured is not None:
            seconds[run.subdir] = measured
    return seconds


def collect(plan: Plan, results: Path, seconds: dict[str, float],
            packed: Packed = NOTHING_PACKED) -> list[dict[str, Any]]:
    """One record per finished run and distribution: p0 from the run's ``eval.json`` (with the
    run's wall time from ``seconds``, :func:`train_seconds`), each named adversary from its
    ``eval_vs_<name>.json``, each shift (``shift/<name>``) from its ``eval_shifts.json``; with
    noisy support labels as extra records. Each report is read from its run's directory, else
    from ``packed`` (:func:`~armeta_rl.reproduce.plan.load_report`). A report that fails its
    schema is not finished (:func:`~armeta_rl.reproduce.plan.finished`) and is left out."""
    records = []
    sources = [(run, EVAL_FILE, INITIAL, INITIAL) for run in plan.runs]
    sources += [(job.learner, Path(job.out).name, "adversarial", job.name) for job in plan.evals
                if job.adversary is not None]
    shift_files = dict.fromkeys((job.learner, Path(job.out).name) for job in plan.evals
                                if job.adversary is None)  # in the plan's order, as a set is not
    reports: dict[tuple[str, str], dict[str, Any] | None] = {}

    def read(run: TrainRun, file: str) -> dict[str, Any] | None:
        if (run.subdir, file) not in reports:
            try:
                report = load_report(results, results / run.subdir / file, packed)
            except ReportInvalid:
                report = None
            reports[(run.subdir, file)] = report
        return reports[(run.subdir, file)]

    for run, file in shift_files:
        sources += [(run, file, name, name) for name in read(run, file) or ()
                    if name.startswith(SHIFT_PREFIX) and not name.endswith("_noisy")]
    for run, file, section, distribution in sources:
        report = read(run, file)
        if report is None or identity_problem(report, run, results, packed) is not None:
            continue
        run_time = seconds.get(run.subdir) if file == EVAL_FILE else None
        for noisy in (False, True):
            name = f"{section}_noisy" if noisy else section
            for record in section_records(report, name, distribution, noisy):
                records.append({"benchmark": run.benchmark, "method": run.method,
                                "variant": run.variant, "seed": run.seed, **record,
                                "train_seconds": run_time})
    return records


def finished_reports(runs: Iterable[TrainRun], results: Path,
                     packed: Packed = NOTHING_PACKED) -> list[dict[str, Any]]:
    """The ``eval.json`` of each of ``runs`` that has finished
    (:func:`~armeta_rl.reproduce.plan.finished_report`), in its directory or ``packed``."""
    reports = (finished_report(results, run, packed) for run in runs)
    return [report for report in reports if report is not None]


def write_csv(records: Sequence[dict[str, Any]], path: Path) -> None:
    """The records as CSV, one column per key (CVaR columns in increasing α), written
    atomically."""
    keys: list[str] = []
    for record in records:
        keys += [k for k in record if k not in keys and k not in KEPT_OUT_OF_CSV]
    cvars = sorted((k for k in keys if cvar_alpha(k) is not None), key=cvar_alpha)
    sems = sorted((k for k in keys if cvar_alpha(k, "cvar_sem_") is not None),
                  key=lambda k: cvar_alpha(k, "cvar_sem_"))
    columns = [k for k in keys if k not in cvars and k not in sems] + cvars + sems
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=columns, restval="", extrasaction="ignore")
    writer.writeheader()
    writer.writerows(records)
    write_text_atomically(path, text.getvalue())


def select(records: Iterable[dict[str, Any]], **where: Any) -> list[dict[str, Any]]:
    """The records whose fields equal ``where``, in seed order."""
    chosen = [r for r in records if all(r.get(k) == v for k, v in where.items())]
    return sorted(chosen, key=lambda r: r["seed"])


def summary(records: Iterable[dict[str, Any]], key: str, **where: Any) -> SeedSummary | None:
    """``key`` of the matching records over seeds, or ``None`` when none has finished."""
    values = [r[key] for r in select(records, **where) if r.get(key) is not None]
    return over_seeds(values) if values else None


def display(name: str) -> str:
    """A method or benchmark as the paper writes it: ``tr_maml`` → TR-MAML, ``sinusoid_normal``
    → Sinusoid-N; other names unchanged."""
    parts = name.split("_")
    if parts[-1] in ("maml", "cnp"):
        return "-".join(p.upper() for p in parts)
    if parts[-1] in ("uniform", "normal") and len(parts) == 2:
        return f"{parts[0].capitalize()}-{parts[1][0].upper()}"
    return name


def progress_note(plan: Plan, results: Path, packed: Packed = NOTHING_PACKED) -> str:
    """How many of the plan's runs (attack runs included) and evaluations have finished, in
    their directories or ``packed`` (a partial sweep says so, and names the runs whose lost
    checkpoints leave evaluations that can never run: :func:`lost_checkpoints`)."""
    trained = (*plan.runs, *plan.attacks)
    done = {run for run in trained if finished(results, run, packed)}
    attacks = sum(run in done for run in plan.attacks)
    left = [job for job in plan.evals if not finished(results, job, packed)]
    counts = (f"{len(done)}/{len(trained)} training runs"
              + (f" (attack runs {attacks}/{len(plan.attacks)})" if plan.attacks else "")
              + f" and {len(plan.evals) - len(left)}/{len(plan.evals)} evaluations finished")
    if len(done) == len(trained) and not left:
        return f"Profile `{plan.profile}`, complete: {counts}."
    blocked = [needs for job in left if (needs := lost_checkpoints(results, job, done))]
    lost = sorted({run.subdir for needs in blocked for run in needs})
    return (f"Profile `{plan.profile}`, **partial**: {counts} (each cell summarizes the seeds "
            "finished so far, so cells may rest on different numbers of seeds)."
            + (f" {cannot_run(len(blocked), len(left))}: {', '.join(lost)} finished without a "
               "checkpoint to load." if blocked else ""))


def cannot_run(blocked: int, left: int) -> str:
    """How many of the ``left`` unfinished evaluations cannot run, in words."""
    if blocked == left:
        return ("The evaluation left cannot run" if left == 1
                else f"The {left} evaluations left cannot run")
    return f"{blocked} of the {left} evaluations left cannot run"


def lost_checkpoints(results: Path, job: EvalJob, done: Collection[TrainRun]) -> list[TrainRun]:
    """The runs ``job`` needs (its learner, the run whose adversary it draws from) that are
    ``done`` (finished, their reports in) without leaving a checkpoint to load: trained before
    their sweep kept checkpoints, or deleted since. A run not yet finished is not among them: it
    will write its checkpoints."""
    return [run for run in (job.learner, job.adversary) if run in done
            and not checkpoint_dirs(results / run.subdir / "checkpoints")]


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    """A Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)
