"""Speed of meta-RL on point navigation: env steps/s and seconds per MAML-TRPO meta-iteration
(20 tasks × 20 episodes × 100 steps; rollouts before and after adaptation and the TRPO step), on
one thread, with the exact second-order KL Hessian-vector products and with them subsampled to 5
or 2 episodes per task (``hvp_episodes``).

It also times one exact Hessian-vector product (conjugate gradient takes 10 per iteration) against
the batched matrix products that no exact product computed by automatic differentiation can avoid.
For v ↦ Σ_k J_k F_k J_k v
(J_k = I − α∇²L^in_k, F_k the KL's Gauss-Newton matrix) the 64 × 64 hidden layer alone takes 16
products of ``[K, E·T, 64] × [K, 64, 64]``: 6 for each Hessian-vector product of the inner loss
(forward-over-reverse: two per bilinear op of its forward and backward pass) and 4 for F_k (2 in
the Jacobian-vector product, 2 in the transposed one). Prints the table and writes it to its
section of docs/benchmarks.md; run ``OMP_NUM_THREADS=1 python benchmarks/bench_point_nav.py``
(``--tasks``, ``--episodes`` smaller for a quick run).
"""

from __future__ import annotations

import argparse
import math

import torch
from tensordict import TensorDict
from timing import as_trained, markdown_table, median_s, write_section
from torch import nn

from armeta_rl.collectors.episodes import PointNavigationCollector
from armeta_rl.envs.point_navigation import PointNavigationEnv
from armeta_rl.learners.maml_trpo import MAMLTRPOLeader, MamlTrpoOptions
from armeta_rl.rl.policy import GaussianMLP
from armeta_rl.tasks import BoxUniform, TaskSpace


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--tasks", type=int, default=20)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    as_trained()
    k, e, steps = args.tasks, args.episodes, 100
    space = TaskSpace(["goal_x", "goal_y"], [-0.5, -0.5], [0.5, 0.5])
    tasks = BoxUniform(space).sample(k)
    rows = []

    env = PointNavigationEnv((k, e), seed=0)
    reset = env.reset(TensorDict({"params": tasks["params"][:, None].expand(k, e, 2)}, [k, e]))
    t = median_s(lambda: env.rollout(steps, tensordict=reset.clone(), auto_reset=False,
                                    break_when_any_done=False), args.repeats)
    rows.append(("env.rollout, random actions", t, k * e * steps / t))

    collector = PointNavigationCollector(episodes=e, seed=0)
    net = GaussianMLP()
    per_task = TensorDict.from_module(net).detach().expand(k).clone()
    t = median_s(lambda: collector.collect(tasks, None, policy=net), args.repeats)
    rows.append(("collect, shared θ", t, k * e * steps / t))
    t = median_s(lambda: collector.collect(tasks, per_task, policy=net), args.repeats)
    rows.append(("collect, per-task θ'_k", t, k * e * steps / t))

    def erm(losses: torch.Tensor) -> torch.Tensor:
        return torch.full_like(losses, 1.0 / losses.numel())

    leader = MAMLTRPOLeader(collector)
    t = median_s(lambda: leader.collect(tasks), args.repeats)
    rows.append(("both rollouts + inner step (sampling)", t, 2 * k * e * steps / t))
    for label, hvp_episodes in (("exact HVP", None), ("HVP on 5 episodes/task", 5),
                                ("HVP on 2 episodes/task", 2)):
        leader = MAMLTRPOLeader(collector, options=MamlTrpoOptions(hvp_episodes=hvp_episodes))
        t = median_s(lambda leader=leader: leader.step(leader.collect(tasks, create_graph=True),
                                                      erm), args.repeats)
        rows.append((f"meta-iteration, {label}", t, 2 * k * e * steps / t))

    leader = MAMLTRPOLeader(collector)
    batch = leader.collect(tasks, create_graph=True)
    weights = erm(torch.zeros(k))
    hvp = leader.kl_hessian_product(batch, weights, leader.surrogate_gradient(batch, weights)[2])
    vector = torch.randn(sum(p.numel() for p in leader.net.parameters()))
    product = median_s(lambda: hvp(vector), 5 * args.repeats)
    rows.append(("one exact KL Hessian-vector product", product, math.nan))
    largest = max((m for m in leader.net.mean if isinstance(m, nn.Linear)),
                  key=lambda layer: layer.weight.numel())
    n_out, n_in = largest.weight.shape
    activations, weight = torch.randn(k, e * steps, n_in), torch.randn(k, n_in, n_out)
    floor = median_s(lambda: [torch.bmm(activations, weight) for _ in range(16)],
                     5 * args.repeats)
    rows.append((f"its 16 [K, E*T, {n_in}] x [K, {n_in}, {n_out}] products", floor, math.nan))

    table = markdown_table(
        ("what", "seconds", "env steps/s"),
        [(what, f"{t:.3f}", "–" if math.isnan(rate) else f"{rate:,.0f}") for what, t, rate in rows],
    )
    body = (f"Point navigation, {k} tasks × {e} episodes × {steps} steps (MAML-TRPO, second order "
            f"through the adaptation; medians of {args.repeats} calls):\n\n{table}\n\n"
            f"Conjugate gradient's 10 exact products: {10 * product:.2f} s measured, at least "
            f"{10 * floor:.2f} s in the matrix products of the largest layer alone.")
    print(body)
    write_section("bench_point_nav", "Meta-RL: point navigation (bench_point_nav.py)", body)

if __name__ == "__main__":
    main()
