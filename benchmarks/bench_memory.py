"""Memory of a training run: peak RSS per benchmark, and whether the resident set stays flat over
a long run.

Each row trains one benchmark in a fresh process, as ``armeta-train`` builds it (glibc keeps freed
memory, ``trainer.keep_freed_memory``; one torch thread), for its number of meta-iterations, and
reads the process's resident set (``/proc/self/statm``) after a tenth of them, at half and at the
end, and its peak (``ru_maxrss``). Growth is the resident set at the end minus after the first
tenth: a run that keeps references to old iterations' tensors (a leak) grows with the iteration
count; one that does not stays within allocator noise. The point robot and the Ant are long per
iteration, so their 500-iteration rows run at reduced sizes (the code paths are the paper's), and
the Ant's paper profile (40 tasks × 20 episodes × 200 steps) has its peak RSS measured over one
iteration.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_memory.py [--rows NAME ...]``; it prints the
table and writes it to its section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from timing import as_trained, markdown_table, peak_rss_mib, trainer_for, workloads, write_section

HERE = Path(__file__).resolve().parent

ROWS = workloads("memory")
"""The training runs, each with its benchmark, method, meta-iterations and overrides."""


def resident_mib() -> float:
    """This process's resident set now, in MiB."""
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def child(name: str) -> None:
    """Train row ``name`` and print its memory figures as one JSON line."""
    as_trained()
    row = ROWS[name]
    benchmark, method, iterations = row["benchmark"], row["method"], row["iterations"]
    overrides = row.get("overrides", [])
    trainer, _ = trainer_for(f"benchmark={benchmark}", f"method={method}", *overrides)
    # a one-iteration row reads all three marks after its only iteration
    marks = {"tenth": max(1, iterations // 10), "half": max(1, iterations // 2),
             "end": iterations}
    figures: dict[str, float] = {}
    start = time.perf_counter()
    for iteration in range(1, iterations + 1):
        trainer.train_iteration()
        figures.update({mark: resident_mib() for mark, at in marks.items() if at == iteration})
    figures["seconds_per_iteration"] = (time.perf_counter() - start) / iterations
    figures["peak"] = peak_rss_mib()
    print(json.dumps(figures))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child)
        return
    table = []
    for name in args.rows:
        result = subprocess.run([sys.executable, __file__, "--child", name], capture_output=True,
                                text=True, env={**os.environ, "OMP_NUM_THREADS": "1",
                                                "PYTHONPATH": os.pathsep.join(
                                                    [str(HERE.parent), str(HERE)])})
        if result.returncode:
            print(result.stderr[-3000:], file=sys.stderr)
            table.append((name, ROWS[name]["method"], ROWS[name]["iterations"], *["–"] * 5,
                          "failed"))
            continue
        f = json.loads(result.stdout.strip().splitlines()[-1])
        method, iterations = ROWS[name]["method"], ROWS[name]["iterations"]
        growth = f["end"] - f["tenth"]
        table.append((name, method, iterations, f"{f['tenth']:.0f}", f"{f['half']:.0f}",
                      f"{f['end']:.0f}", f"{growth:+.0f}", f"{f['peak']:.0f}",
                      f"{1000 * f['seconds_per_iteration']:.0f}"))
        print(table[-1], flush=True)
        # written after every row: the last rows (the Ant) take long
        load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
        body = ("Resident set (MiB) of a training run in its own process, after a tenth of its "
                "meta-iterations, at half and at the end; growth = end − tenth; peak = the "
                f"process's peak RSS (load average after the last row {load}):\n\n"
                + markdown_table(("run", "method", "iterations", "RSS at 1/10", "RSS at 1/2",
                                  "RSS at end", "growth", "peak RSS", "ms per iteration"),
                                 table))
        write_section("bench_memory", "Memory over a run (bench_memory.py)", body)
    print(body)


if __name__ == "__main__":
    main()
