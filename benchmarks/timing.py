"""Wall-clock timing shared by the benchmark scripts (run as ``python benchmarks/<name>.py``), and
the writer of their sections of docs/benchmarks.md: every script replaces its own section, between
``<!-- name:start -->`` and ``<!-- name:end -->``, with its tables, its command and the date."""

from __future__ import annotations

import datetime
import os
import platform
import shlex
import statistics
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import torch


def wall_times(
    fn: Callable[[], object],
    repeats: int,
    warmup: int = 1,
    clock: Callable[[], float] = time.perf_counter,
) -> list[float]:
    """Seconds taken by each of ``repeats`` calls of ``fn``, after ``warmup`` untimed calls, on
    ``clock`` (wall time; ``time.process_time`` gives this process's CPU time, less sensitive to
    other processes)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = clock()
        fn()
        times.append(clock() - start)
    return times


def reference_product_ms(repeats: int = 50) -> float:
    """Median ms of one ``[16, 190, 128] × [16, 128, 128]`` float32 ``bmm``, the largest product of
    the system-identification MAML step: a yardstick of how fast the machine runs at the moment
    (a shared machine has fast and slow spells), so that tables taken at different times can be
    compared."""
    activations, weights = torch.randn(16, 190, 128), torch.randn(16, 128, 128)
    times = wall_times(lambda: torch.bmm(activations, weights), repeats, warmup=5)
    return 1000 * statistics.median(times)


def alternating_ratios(
    reference: Callable[[], object],
    variant: Callable[[], object],
    calls: int,
    rounds: int,
    use_reference: Callable[[], None] = lambda: None,
    use_variant: Callable[[], None] = lambda: None,
) -> tuple[list[float], list[float]]:
    """Median seconds of ``calls`` calls of ``reference`` and of ``variant``, taking turns
    ``rounds`` times (after one untimed turn each), so that a shared machine's slow spells fall
    on both alike; ``use_reference`` / ``use_variant`` switch between them before each turn when
    both are the same function. Returns the reference's and the variant's turn medians."""
    def turn(use: Callable[[], None], fn: Callable[[], object]) -> float:
        use()
        return statistics.median(wall_times(fn, calls, warmup=0))

    turn(use_reference, reference)
    turn(use_variant, variant)
    pairs = [(turn(use_reference, reference), turn(use_variant, variant)) for _ in range(rounds)]
    use_reference()
    return [r for r, _ in pairs], [v for _, v in pairs]


DOCS = Path(__file__).resolve().parents[1] / "docs"
BENCHMARKS_PAGE = DOCS / "benchmarks.md"


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
        command = "OMP_NUM_THREADS=1 python " + " ".join(
            [f"benchmarks/{Path(sys.argv[0]).name}", *map(shlex.quote, sys.argv[1:])])
    text = page.read_text() if page.exists() else ""
    page.write_text(replace_section(text, name, section(title, command, body, machine)))
    print(f"wrote the {name} section of {page}")
