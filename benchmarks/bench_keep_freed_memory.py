"""``trainer.keep_freed_memory`` on against off: time per meta-iteration of ``armeta-train`` runs.

The switch sets glibc's allocator for the whole process, so it cannot take turns inside one
process as the switches of ``bench_speed_options.py`` do: each round runs one ``armeta-train``
process with the switch off and one with it on, in turn, and reads each run's
``time/iteration_ms`` log (the median over its iterations after the first fifth). Prints the table
and writes it to its section of docs/benchmarks.md; run
``OMP_NUM_THREADS=1 python benchmarks/bench_keep_freed_memory.py`` (``--rounds``,
``--iterations``, ``--benchmark`` to change the runs).
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from timing import markdown_table, write_section

ROOT = Path(__file__).resolve().parents[1]


def iteration_ms(benchmark: str, iterations: int, keep: bool) -> float:
    """Median ms per meta-iteration of one AR-MAML ``armeta-train`` run, its first fifth left
    out (warm-up)."""
    with tempfile.TemporaryDirectory() as out:
        subprocess.run(
            [sys.executable, "-c", "from armeta_rl.cli import train; train()",
             f"benchmark={benchmark}", "method=ar_maml", f"trainer.iterations={iterations}",
             f"trainer.keep_freed_memory={str(keep).lower()}", "trainer.log_every=1",
             "logger=csv", "trainer.progress=false", "eval.n_tasks=4",
             "trainer.checkpoint_every=100000", f"hydra.run.dir={out}"],
            cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1", "WANDB_MODE": "offline",
                           "PYTHONPATH": str(ROOT)},
            check=True, capture_output=True,
        )
        log = (Path(out) / "logs/scalars/time/iteration_ms.csv").read_text()
        rows = list(csv.reader(log.splitlines()))
    return statistics.median(float(value) for _, value in rows[len(rows) // 5:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--benchmark", default="point_nav")
    parser.add_argument("--iterations", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    off, on = [], []
    for round_ in range(args.rounds):
        off.append(iteration_ms(args.benchmark, args.iterations, keep=False))
        on.append(iteration_ms(args.benchmark, args.iterations, keep=True))
        print(f"round {round_}: off {off[-1]:.0f} ms, on {on[-1]:.0f} ms", flush=True)
    ratios = ", ".join(f"{b / a:.2f}" for a, b in zip(off, on))
    table = markdown_table(
        ["`trainer.keep_freed_memory`", "ms per meta-iteration (median of rounds)",
         "on/off per round"],
        [["false", f"{statistics.median(off):.0f}", ""],
         ["true", f"{statistics.median(on):.0f}", ratios]],
    )
    body = (f"`armeta-train benchmark={args.benchmark} method=ar_maml "
            f"trainer.iterations={args.iterations}`, one process per run, the switch off and on "
            f"in turn for {args.rounds} rounds; per run the median of its iterations after the "
            f"first fifth:\n\n{table}")
    print(table)
    write_section("bench_keep_freed_memory", "Keeping freed memory (bench_keep_freed_memory.py)",
                  body)


if __name__ == "__main__":
    main()
