"""Where a meta-iteration's time goes: the Python functions of ``--iterations`` meta-iterations of
one benchmark and method under ``cProfile``, sorted by cumulative time, after the median time of
as many unprofiled iterations (the profiler's own cost inflates the profiled ones).

The trainer is ``armeta-train``'s (``timing.trainer_for``, with its allocator setting), built
from the config with the overrides given; ``device=cuda`` profiles on the GPU (each iteration
then ends with a device synchronization, so that queued kernels count where they ran).

Run: ``OMP_NUM_THREADS=1 python benchmarks/profile_iteration.py --benchmark
acrobot_uniform_paper --method ar_maml [override ...] [--iterations 20] [--lines 40]
[--out FILE]``; it prints the profile and, with ``--out``, writes it there too.

``--curvature`` profiles, instead, one MAML-TRPO leader's KL curvature product (the conjugate
gradient's Hessian-vector product, most of a meta-RL iteration beyond its rollouts) on a batch
the leader collects on the trainer's first proposed tasks: the median product, then
``torch.profiler``'s operators by their own time over ``--iterations`` more, the matrix products
(``timing.PRODUCTS``, those ``products_ms`` replays) against the elementwise rest. Keep
``--iterations`` small at large sizes: the profiler keeps a record per operator call.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import statistics
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from timing import PRODUCTS, as_trained, trainer_for, wall_times

if TYPE_CHECKING:
    from armeta_rl.learners.maml_trpo import MAMLTRPOLeader
    from armeta_rl.trainers.game import GameTrainer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--benchmark", required=True)
    parser.add_argument("--method", required=True)
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--lines", type=int, default=40, help="functions to list")
    parser.add_argument("--out", type=Path, help="also write the profile to this file")
    parser.add_argument("--curvature", action="store_true",
                        help="profile the MAML-TRPO leader's KL curvature product instead")
    args, overrides = parser.parse_known_args()
    if args.iterations < 1:
        parser.error(f"--iterations must be at least 1, got {args.iterations}")
    as_trained()
    trainer, players = trainer_for(f"benchmark={args.benchmark}", f"method={args.method}",
                                   *overrides)
    if args.curvature:
        if not hasattr(players.leader, "kl_hessian_product"):
            parser.error(f"--curvature needs a MAML-TRPO leader; {args.benchmark} has "
                         f"{type(players.leader).__name__}")
        report = curvature_profile(trainer, players.leader, args.iterations, args.warmup,
                                   args.lines)
        print(f"{args.benchmark} {args.method} {' '.join(overrides)}: {report}")
        if args.out is not None:
            args.out.write_text(report)
        return

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


def curvature_profile(trainer: GameTrainer, leader: MAMLTRPOLeader, products: int,
                      warmup: int, lines: int) -> str:
    """The median of ``products`` KL curvature products of ``leader`` (after ``warmup``) on a
    batch it collects on ``trainer``'s first proposed tasks, weighted equally, and
    ``torch.profiler``'s table of the operators by their own time over as many more, with the
    matrix products' share of it."""
    tasks = trainer.principle.propose(trainer.options.meta_batch)
    batch = leader.collect(tasks, create_graph=True)
    weights = torch.full((tasks.batch_size[0],), 1.0 / tasks.batch_size[0])
    _, gradient, graph = leader.surrogate_gradient(batch, weights)
    product = leader.kl_hessian_product(batch, weights, graph)
    vector = torch.randn_like(gradient)
    times = wall_times(lambda: product(vector), products, warmup=warmup)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profiler:
        for _ in range(products):
            product(vector)
    operators = [e for e in profiler.key_averages() if e.key.startswith("aten::")]
    total = sum(e.self_cpu_time_total for e in operators)
    matrix = sum(e.self_cpu_time_total for e in operators if e.key in PRODUCTS)
    shape = "×".join(str(n) for n in batch.valid["mask"].shape)
    subset = ("" if leader.hvp_episodes is None
              else f", the curvature on {leader.hvp_episodes} episodes a task")
    return (f"median KL curvature product {1000 * statistics.median(times):.1f} ms on a "
            f"{shape} meta-batch{subset} ({products} products after {warmup} warm-up; "
            f"{gradient.numel()} policy parameters); matrix products {100 * matrix / total:.0f} "
            f"% of the operators' own time, the rest elementwise and bookkeeping; "
            f"torch.profiler over {products} more:\n"
            + profiler.key_averages().table(sort_by="self_cpu_time_total", row_limit=lines))


if __name__ == "__main__":
    main()
