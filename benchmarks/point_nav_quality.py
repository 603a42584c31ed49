"""Quality check of MAML-TRPO on plain point navigation (issue 5): ``maml`` (ERM, goals uniform on
[-0.5, 0.5]²), 20 tasks per meta-iteration, fixed seed. Prints the learning curve of the mean
return before and after adaptation, then an evaluation on 100 fresh tasks.

Reference (pytorch-maml-rl, same configuration, 100 meta-iterations): about −38 before and −16
after adaptation. Run: ``OMP_NUM_THREADS=1 python benchmarks/point_nav_quality.py``.
"""

from __future__ import annotations

import argparse
import time

import torch

from armeta_rl.collectors.episodes import PointNavigationCollector
from armeta_rl.rl.maml_trpo import MAMLTRPOLeader
from armeta_rl.tasks import BoxUniform, TaskSpace


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--iterations", type=int, default=100)
    parser.add_argument("--meta-batch", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--hvp-episodes", type=int, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    tasks = BoxUniform(TaskSpace(["goal_x", "goal_y"], [-0.5, -0.5], [0.5, 0.5]))
    collector = PointNavigationCollector(seed=args.seed)
    leader = MAMLTRPOLeader(collector, hvp_episodes=args.hvp_episodes)

    def erm(losses: torch.Tensor) -> torch.Tensor:
        return torch.full_like(losses, 1.0 / losses.numel())

    print(f"{'iter':>4} {'return_pre':>11} {'return_post':>12} {'ls_step':>8} {'kl':>8} "
          f"{'seconds':>8}", flush=True)
    start = time.perf_counter()
    for iteration in range(args.iterations):
        tick = time.perf_counter()
        out = leader.step(tasks.sample(args.meta_batch), erm)
        update = leader.last_update
        print(f"{iteration:>4} {out['return_pre'].mean().item():>11.2f} "
              f"{out['return_post'].mean().item():>12.2f} "
              f"{update['trpo/line_search_steps']:>8.0f} {update['trpo/kl']:>8.5f} "
              f"{time.perf_counter() - tick:>8.2f}", flush=True)
    returns = -leader.evaluate(tasks.sample(100))
    print(f"total {time.perf_counter() - start:.0f} s; evaluation on 100 new tasks: "
          f"post-adaptation return {returns.mean().item():.2f} ± "
          f"{returns.std().item() / 100 ** 0.5:.2f}", flush=True)


if __name__ == "__main__":
    main()
