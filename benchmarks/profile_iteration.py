"""Where a meta-iteration's time goes: the Python functions of ``--iterations`` meta-iterations of
one benchmark and method under ``cProfile``, sorted by cumulative time, after the median time of
as many unprofiled iterations (the profiler's own cost inflates the profiled ones).

The trainer is ``armeta-train``'s (``timing.trainer_for``, with its allocator setting), built
from the config with the overrides given; ``device=cuda`` profiles on the GPU (each iteration
then ends with a device synchronization, so that queued kernels count where they ran).

Run: ``OMP_NUM_THREADS=1 python benchmarks/profile_iteration.py --benchmark
acrobot_uniform_paper --method ar_maml [override ...] [--iterations 20] [--lines 40]
[--out FILE]``; it prints the profile and, with ``--out``, writes it there too.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import statistics
from pathlib import Path

import torch
from timing import as_trained, trainer_for, wall_times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--benchmark", required=True)
    parser.add_argument("--method", required=True)
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--lines", type=int, default=40, help="functions to list")
    parser.add_argument("--out", type=Path, help="also write the profile to this file")
    args, overrides = parser.parse_known_args()
    if args.iterations < 1:
        parser.error(f"--iterations must be at least 1, got {args.iterations}")
    as_trained()
    trainer, _ = trainer_for(f"benchmark={args.benchmark}", f"method={args.method}",
                             *overrides)

    def iteration() -> None:
        trainer.train_iteration()
        if torch.cuda.is_initialized():
            torch.cuda.synchronize()

    times = wall_times(iteration, args.iterations, warmup=args.warmup)
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(args.iterations):
        iteration()
    profiler.disable()
    text = io.StringIO()
    pstats.Stats(profiler, stream=text).sort_stats("cumulative").print_stats(args.lines)
    report = (f"{args.benchmark} {args.method} {' '.join(overrides)}: median meta-iteration "
              f"{1000 * statistics.median(times):.1f} ms unprofiled ({args.iterations} "
              f"iterations after {args.warmup} warm-up); cProfile of {args.iterations} more:\n"
              + text.getvalue())
    print(report)
    if args.out is not None:
        args.out.write_text(report)


if __name__ == "__main__":
    main()
