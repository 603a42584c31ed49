"""The benchmark harness, and the entry of every comparison declared as data:
``python -m benchmarks.timing NAME [--rounds N] [--calls N] [override ...]`` runs the comparison
``NAME`` under ``turns`` in ``benchmarks/workloads.yaml`` (no script of its own). The other
benchmark scripts (``python benchmarks/<name>.py``) take their workloads, timing and tables from
here too.

* workloads: :func:`workloads` reads a benchmark's part of ``benchmarks/workloads.yaml`` (the
  workloads as data), :func:`trainer_for` builds a run's trainer from config overrides as
  ``armeta-train`` builds it, :func:`as_trained` sets the process up as ``armeta-train`` does;
* timing: :func:`wall_times` and :func:`median_s` (calls of one function), :func:`in_turns`
  (several functions taking turns in one session, so that a shared machine's slow spells fall on
  all alike: the way two forms are compared) with :func:`ratio_cell` for the ratios of turns,
  :func:`compare_in_turns` (trainers of config overrides in turns, from ``workloads.yaml``),
  :func:`peak_rss_mib` and :func:`reference_product_ms` (a yardstick of the machine's speed);
* tables: :func:`markdown_table` and :func:`write_section`, which replaces the script's section of
  docs/benchmarks.md (between ``<!-- name:start -->`` and ``<!-- name:end -->``) with its tables,
  its command, the date and the machine.
"""

from __future__ import annotations

import dataclasses
import datetime
import os
import platform
import resource
import shlex
import statistics
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from armeta_rl.trainers.game import GameTrainer
    from armeta_rl.trainers.players import Players

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
BENCHMARKS_PAGE = DOCS / "benchmarks.md"
WORKLOADS = Path(__file__).with_name("workloads.yaml")
REFERENCE_ROWS = DOCS / "results" / "reference" / "rows.json"
"""Each reference workload's latest medians (``bench_reference.py`` writes them; the GPU check's
point-robot target reads them)."""


# -- workloads ----------------------------------------------------------------------------------

def workloads(key: str) -> dict:
    """The workloads of ``key`` (a benchmark's part of ``benchmarks/workloads.yaml``)."""
    import yaml

    return yaml.safe_load(WORKLOADS.read_text())[key]


def trainer_for(*overrides: str) -> tuple[GameTrainer, Players]:
    """A seeded ``GameTrainer`` of the ``armeta-train`` config with ``overrides``, its players
    built as the CLI builds them (no logger, no progress bar), and the players."""
    from hydra import compose, initialize_config_dir

    from armeta_rl.cli import config_dir
    from armeta_rl.config import validate
    from armeta_rl.trainers.game import GameTrainer
    from armeta_rl.trainers.players import build_players

    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        cfg = compose("train", overrides=[*overrides, "trainer.progress=false", "logger=none"])
    config = validate(cfg)
    players = build_players(config)
    trainer = GameTrainer(players.leader, players.principle,
                          dataclasses.replace(config.trainer, iterations=10**9))
    return trainer, players


def as_trained() -> None:
    """This process set up as ``armeta-train`` sets up a run (one torch thread here, glibc keeping
    freed memory: ``trainer.keep_freed_memory``), torch's generator seeded with 0."""
    from armeta_rl.allocator import keep_freed_memory

    torch.set_num_threads(1)
    keep_freed_memory()
    torch.manual_seed(0)


# -- timing -------------------------------------------------------------------------------------

def wall_times(
    fn: Callable[[], object],
    repeats: int,
    warmup: int = 1,
    sync: Callable[[], object] = lambda: None,
    budget_s: float = float("inf"),
) -> list[float]:
    """Wall seconds taken by each of ``repeats`` calls of ``fn``, after ``warmup`` untimed calls;
    ``sync`` waits for queued device work before each reading (e.g.
    ``torch.cuda.synchronize``); no call starts after ``budget_s`` seconds of timed calls once
    one has been timed."""
    for _ in range(warmup):
        fn()
    sync()
    times: list[float] = []
    while len(times) < repeats and (not times or sum(times) < budget_s):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return times


def median_s(fn: Callable[[], object], repeats: int, warmup: int = 1, **kwargs) -> float:
    """Median seconds of ``repeats`` calls of ``fn`` (:func:`wall_times`)."""
    return statistics.median(wall_times(fn, repeats, warmup, **kwargs))


def in_turns(
    rows: dict[str, Callable[[], object]],
    calls: int,
    rounds: int,
    warmup: int = 1,
    between: Callable[[], float] | None = None,
) -> tuple[dict[str, list[list[float]]], dict[str, list[float]]]:
    """Every row's ``rounds`` turns of ``calls`` timed calls, the rows taking turns (after
    ``warmup`` untimed calls of each; the first row of a round rotates, so that no row always
    follows the same one), so that a shared machine's slow spells fall on all rows alike.
    Returns each row's turns (their calls' seconds) and, where ``between`` is given (a yardstick
    taken after every turn and once before the first), each turn's mean of the yardsticks taken
    just before and just after it."""
    for fn in rows.values():
        for _ in range(warmup):
            fn()
    labels = list(rows)
    turns: dict[str, list[list[float]]] = {label: [] for label in labels}
    marks: dict[str, list[float]] = {label: [] for label in labels}
    before = between() if between else float("nan")
    for index in range(rounds):
        for label in labels[index % len(labels):] + labels[:index % len(labels)]:
            turns[label].append(wall_times(rows[label], calls, warmup=0))
            after = between() if between else float("nan")
            marks[label].append((before + after) / 2)
            before = after
    return turns, marks


def turn_medians(turns: list[list[float]]) -> list[float]:
    """The median seconds of each turn."""
    return [statistics.median(turn) for turn in turns]


def ratio_cell(numerators: Sequence[float], denominators: Sequence[float],
               digits: int = 2) -> str:
    """The median of the per-round ratios and their range, as a table cell: ``**1.23×**
    (1.10–1.40)``."""
    ratios = [a / b for a, b in zip(numerators, denominators, strict=True)]
    return (f"**{statistics.median(ratios):.{digits}f}×** ({min(ratios):.{digits}f}–"
            f"{max(ratios):.{digits}f})")


def peak_rss_mib() -> float:
    """This process's peak resident set size in MiB (Linux reports ``ru_maxrss`` in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def reference_product_ms(repeats: int = 50) -> float:
    """Median ms of one ``[16, 190, 128] × [16, 128, 128]`` float32 ``bmm``, the largest product of
    the system-identification MAML step: a yardstick of how fast the machine runs at the moment
    (a shared machine has fast and slow spells), so that tables taken at different times can be
    compared."""
    activations, weights = torch.randn(16, 190, 128), torch.randn(16, 128, 128)
    return 1000 * median_s(lambda: torch.bmm(activations, weights), repeats, warmup=5)


# -- tables and sections ------------------------------------------------------------------------

def markdown_table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """A Markdown table with ``header`` and one line per row (cells as ``str`` gives them)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def markers(name: str) -> tuple[str, str]:
    """The HTML comments that open and close script ``name``'s section of a page."""
    return f"<!-- {name}:start -->", f"<!-- {name}:end -->"


def replace_section(page: str, name: str, section: str) -> str:
    """``page`` with the text between ``name``'s markers replaced by ``section`` (the markers
    appended at the end if the page has none yet); everything outside them is kept as it is."""
    start, end = markers(name)
    block = f"{start}\n{section.strip()}\n{end}"
    if start not in page:
        return page.rstrip("\n") + "\n\n" + block + "\n"
    head, rest = page.split(start, 1)
    if end not in rest:
        raise ValueError(f"{name}: '{start}' without '{end}'")
    return head + block + rest.split(end, 1)[1]


def this_machine() -> str:
    """This machine as the benchmark pages name it: architecture, CPUs, torch, its CPU kernels
    and threads."""
    return (f"{platform.machine()}, {os.cpu_count()} logical CPUs, torch {torch.__version__} "
            f"({torch.backends.cpu.get_cpu_capability()} kernels), {torch.get_num_threads()} "
            f"thread")


def section(title: str, command: str, body: str, machine: str | None = None) -> str:
    """A script's section: its title, the command that produced it, the date, the machine and its
    load (other processes slow a shared machine down; ``machine`` where the figures were measured
    elsewhere, e.g. rows of a GPU machine reported here), and ``body`` (the tables)."""
    if machine is None:
        load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
        machine = f"{this_machine()}; load average at the end {load}"
    return (f"## {title}\n\n`{command}`, run on {datetime.date.today().isoformat()} "
            f"({machine}).\n\n{body.strip()}\n")


def write_section(name: str, title: str, body: str, page: Path = BENCHMARKS_PAGE,
                  command: str | None = None, machine: str | None = None) -> None:
    """Write script ``name``'s section of ``page`` (docs/benchmarks.md by default), leaving the
    other scripts' sections untouched; the command is ``command``, by default this process's own
    command line, and the machine ``machine``, by default this one."""
    if command is None:
        script = Path(sys.argv[0]).resolve()
        shown = ("-m benchmarks.timing" if script == Path(__file__).resolve()
                 else script.relative_to(ROOT) if script.is_relative_to(ROOT)
                 else Path("benchmarks", script.name))
        command = "OMP_NUM_THREADS=1 python " + " ".join(
            [str(shown), *map(shlex.quote, sys.argv[1:])])
    text = page.read_text() if page.exists() else ""
    page.write_text(replace_section(text, name, section(title, command, body, machine)))
    print(f"wrote the {name} section of {page}")


# -- trainers in turns: the comparisons under ``turns`` in workloads.yaml ----------------------

def compare_in_turns(name: str, argv: Sequence[str] | None = None) -> str:
    """Run comparison ``name`` under ``turns`` in ``workloads.yaml`` (command-line options
    ``--rounds``, ``--calls``, ``--benchmarks``, ``--compile``/``--no-compile``, ``--no-doc``;
    other arguments are config overrides of every row), write its table into its section of each
    of its pages (unless ``--no-doc``), and return the section's body.

    Every row's trainer runs its warm-up calls (timed together: compiles, actors' starts and env
    builds fall there), then the rows of a group take turns (:func:`in_turns`), with the
    machine's yardstick (:func:`reference_product_ms`) taken between turns. A row's ms are the
    median of its turn medians; its fast-spell median is the median of its turns whose yardstick
    is at most the lower quartile of the group's (the code's cost in the run's fastest spells);
    its ratio is its turn over the group's first row's turn of the same round."""
    import argparse

    spec = workloads("turns")[name]
    parser = argparse.ArgumentParser(description=spec["about"])
    parser.add_argument("--rounds", "--turns", type=int, default=spec["rounds"])
    parser.add_argument("--calls", type=int, default=spec["calls"], help="calls per turn")
    parser.add_argument("--benchmarks", nargs="+", help="the groups run (default: all)")
    parser.add_argument("--compile", action="store_true", help="run the rows that compile")
    parser.add_argument("--no-compile", action="store_true", help="skip the rows that compile")
    parser.add_argument("--no-doc", action="store_true", help="print the table only")
    args, overrides = parser.parse_known_args(argv)
    if args.rounds < 1:
        parser.error(f"--rounds must be at least 1, got {args.rounds}")
    compiling = args.compile or (spec.get("compile") != "opt-in" and not args.no_compile)
    as_trained()
    table, marks_seen = [], []
    for group in spec["groups"]:
        wanted = {label: row for label, row in group["rows"].items()
                  if compiling or not any(o.endswith("compile=true") for o in row)}
        if args.benchmarks and group["benchmark"] not in args.benchmarks or len(wanted) < 2:
            continue  # a group left without a row to compare
        rows, warmups = {}, {}
        for label, row in wanted.items():
            trainer, _ = trainer_for(f"benchmark={group['benchmark']}", *spec.get("base", []),
                                     *row, *overrides)
            warmups[label] = sum(wall_times(trainer.train_iteration, spec["warmup"], warmup=0))
            rows[label] = trainer.train_iteration
        turns, marks = in_turns(rows, args.calls, args.rounds, warmup=0,
                                between=lambda: reference_product_ms(repeats=5))
        every = [mark for label in rows for mark in marks[label]]
        fast = statistics.quantiles(every, n=4)[0] if len(every) > 1 else every[0]
        marks_seen += every
        first = turn_medians(turns[next(iter(rows))])
        for label in rows:
            medians = turn_medians(turns[label])
            quick = [t for mark, turn in zip(marks[label], turns[label]) if mark <= fast
                     for t in turn]
            table.append((group["benchmark"], label, f"{1000 * statistics.median(medians):.1f}",
                          f"{1000 * min(min(turn) for turn in turns[label]):.1f}",
                          f"{1000 * statistics.median(quick):.1f}" if quick else "–",
                          ratio_cell(medians, first), f"{warmups[label]:.1f}"))
            print(" | ".join(table[-1]), flush=True)
    body = (f"{spec['about']} Per row: {spec['warmup']} warm-up calls (their seconds in the last "
            f"column, compiles included), then {args.rounds} rounds of {args.calls} calls, the "
            "rows of a benchmark taking turns (`timing.compare_in_turns`); ms: median of the turn "
            "medians; fast-spell: the turns whose machine yardstick (`timing.reference_product_ms`"
            f", median {statistics.median(marks_seen):.2f} ms, range {min(marks_seen):.2f}–"
            f"{max(marks_seen):.2f} ms) was at most the benchmark's lower quartile; ratio: the "
            "row's turn over the first row's turn of the same round.\n\n"
            + markdown_table(("benchmark", "row", "median ms", "min ms", "fast-spell median ms",
                              "× first row (median, range)", f"first {spec['warmup']} calls s"),
                             table))
    print(body)
    for page in [] if args.no_doc else spec["pages"]:
        write_section(name, spec["title"], body, DOCS / page)
    return body


def main(argv: Sequence[str]) -> None:
    """``python -m benchmarks.timing NAME [option ...] [override ...]``: comparison ``NAME``
    under ``turns`` in ``workloads.yaml`` (:func:`compare_in_turns`); an unknown name gets one
    line naming the known ones (exit code 2)."""
    names = list(workloads("turns"))
    if argv and argv[0] in ("-h", "--help"):
        print("usage: python -m benchmarks.timing NAME [--help] [option ...] [override ...]\n"
              f"NAME: {', '.join(names)} (the comparisons under 'turns' in "
              "benchmarks/workloads.yaml; NAME --help lists the options)")
        return
    if not argv or argv[0] not in names:
        got = repr(argv[0]) if argv else "nothing"
        print(f"benchmarks.timing: NAME = {got}: allowed: {', '.join(names)} (the comparisons "
              "under 'turns' in benchmarks/workloads.yaml)", file=sys.stderr)
        sys.exit(2)
    compare_in_turns(argv[0], argv[1:])


if __name__ == "__main__":
    main(sys.argv[1:])
