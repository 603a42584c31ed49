"""Speed of meta-RL on point navigation: env steps/s and seconds per MAML-TRPO meta-iteration
(20 tasks × 20 episodes × 100 steps; rollouts before and after adaptation and the TRPO step), on
one thread, with the exact second-order KL Hessian-vector products and with them subsampled to 5
or 2 episodes per task (``hvp_episodes``). Prints a table; run
``OMP_NUM_THREADS=1 python benchmarks/bench_point_nav.py``.
"""

from __future__ import annotations

import argparse
import statistics
from collections.abc import Callable

import torch
from tensordict import TensorDict
from timing import wall_times

from armeta_rl.allocator import keep_freed_memory
from armeta_rl.collectors.episodes import PointNavigationCollector
from armeta_rl.envs.point_navigation import PointNavigationEnv
from armeta_rl.rl.maml_trpo import MAMLTRPOLeader
from armeta_rl.rl.policy import GaussianMLP
from armeta_rl.tasks import BoxUniform, TaskSpace


def seconds(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of ``repeats`` calls after one warm-up call."""
    return statistics.median(wall_times(fn, repeats))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--tasks", type=int, default=20)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    keep_freed_memory()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    k, e, steps = args.tasks, args.episodes, 100
    space = TaskSpace(["goal_x", "goal_y"], [-0.5, -0.5], [0.5, 0.5])
    tasks = BoxUniform(space).sample(k)
    rows = []

    env = PointNavigationEnv((k, e), seed=0)
    reset = env.reset(TensorDict({"goal": tasks["params"][:, None].expand(k, e, 2)}, [k, e]))
    t = seconds(lambda: env.rollout(steps, tensordict=reset.clone(), auto_reset=False,
                                    break_when_any_done=False), args.repeats)
    rows.append(("env.rollout, random actions", t, k * e * steps / t))

    collector = PointNavigationCollector(episodes=e, seed=0)
    net = GaussianMLP()
    per_task = TensorDict.from_module(net).detach().expand(k).clone()
    t = seconds(lambda: collector.collect(tasks, None, policy=net), args.repeats)
    rows.append(("collect, shared θ", t, k * e * steps / t))
    t = seconds(lambda: collector.collect(tasks, per_task, policy=net), args.repeats)
    rows.append(("collect, per-task θ'_k (vmap)", t, k * e * steps / t))

    def erm(losses: torch.Tensor) -> torch.Tensor:
        return torch.full_like(losses, 1.0 / losses.numel())

    leader = MAMLTRPOLeader(collector)
    t = seconds(lambda: leader.collect_meta_batch(tasks), args.repeats)
    rows.append(("both rollouts + inner step (sampling)", t, 2 * k * e * steps / t))
    for label, hvp_episodes in (("exact HVP", None), ("HVP on 5 episodes/task", 5),
                                ("HVP on 2 episodes/task", 2)):
        leader = MAMLTRPOLeader(collector, hvp_episodes=hvp_episodes)
        t = seconds(lambda leader=leader: leader.step(tasks, erm), args.repeats)
        rows.append((f"meta-iteration, {label}", t, 2 * k * e * steps / t))

    print(f"point_nav, {k} tasks x {e} episodes x {steps} steps, torch threads = "
          f"{torch.get_num_threads()}")
    print(f"{'what':<42} {'seconds':>9} {'env steps/s':>12}")
    for what, t, rate in rows:
        print(f"{what:<42} {t:>9.3f} {rate:>12.0f}")


if __name__ == "__main__":
    main()
