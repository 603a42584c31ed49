"""How far the follower can move p_φ, per coordinate of the task box, under each step rule
(docs/adversary.md).

Against a fixed loss that grows along one identifier (L(τ) = that identifier scaled to [0, 1],
plus N(0, 0.05²) noise per task, K = 20 tasks an update), the follower takes ``--updates``
ascent steps with λ = 0; the table gives KL(p0 ‖ p_φ) at the end (non-negative estimator, 20,000
draws of p0) per box, coordinate and rule. The boxes are HalfCheetah-Vel's (one identifier, the
target velocity) and HalfCheetah-MassVel's (target velocity, mass scale), with the spline flow
both use. The rules: Adam at the committed rate 0.5 / updates, cosine-annealed (the experiments'
``risk.ar.lr = 0.5 / iterations``), and natural steps of KL δ per update
(``risk.ar.step=natural``). Where a rule reaches clearly different KL on the two coordinates of
one box, the order of the identifiers decides what the adversary can do; where it reaches the
same KL at every run length, the step budget, not the loss, holds it.

Run: ``OMP_NUM_THREADS=1 python studies/adversary_mobility.py [--updates 20 400]``; it prints the
table and writes it to its section of docs/adversary.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from armeta_rl.adversary import FlowAdversary
from armeta_rl.risk.adversarial import AdversarialPrinciple, ArOptions
from armeta_rl.tasks import BoxUniform, TaskSpace

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from timing import DOCS, markdown_table, write_section  # noqa: E402 (the benchmarks' writer)

BOXES = {
    "HalfCheetah-Vel": TaskSpace(["goal_velocity"], [0.0], [2.0]),
    "HalfCheetah-MassVel": TaskSpace(["goal_velocity", "mass_scale"], [0.0, 0.75], [2.0, 1.25]),
}
TASKS = 20
NOISE = 0.05


def rules(updates: int) -> dict[str, dict]:
    """The step rules compared, as ``risk.ar`` keys, at a run of ``updates`` updates."""
    return {"Adam, 0.5 / updates, cosine": {"lr": 0.5 / updates},
            "natural, δ = 0.002": {"step": "natural", "max_kl": 0.002},
            "natural, δ = 0.01": {"step": "natural", "max_kl": 0.01}}


def reachable_kl(space: TaskSpace, coordinate: int, rule: dict, updates: int,
                 seed: int = 0) -> tuple[float, float]:
    """KL(p0 ‖ p_φ) and its standard error after ``updates`` steps of ``rule`` against the fixed
    loss that grows along ``coordinate``."""
    torch.manual_seed(seed)
    adversary = FlowAdversary(space, BoxUniform(space))
    principle = AdversarialPrinciple(adversary, ArOptions(lam=0.0, **rule), total_updates=updates)
    low, high = space.bounds(torch.float64)
    for _ in range(updates):
        tasks = principle.propose(TASKS)
        scaled = (tasks["params"][:, coordinate] - low[coordinate]) / (high - low)[coordinate]
        principle.update(tasks, scaled + NOISE * torch.randn(TASKS, dtype=torch.float64))
    kl, sem = adversary.kl_from(adversary.base, 20_000)
    return float(kl), float(sem)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--updates", type=int, nargs="+", default=[20, 400])
    args = parser.parse_args()
    torch.set_num_threads(1)
    header = ["box", "coordinate", "updates", *rules(1)]
    rows = []
    for name, space in BOXES.items():
        for coordinate, identifier in enumerate(space.names):
            for updates in args.updates:
                cells = [reachable_kl(space, coordinate, rule, updates)
                         for rule in rules(updates).values()]
                rows.append([name, identifier, str(updates),
                             *(f"{kl:.3f} ± {sem:.3f}" for kl, sem in cells)])
                print(" | ".join(rows[-1]), flush=True)
    body = (f"KL(p0 ‖ p_φ) ± its standard error after the given number of follower updates "
            f"(λ = 0, {TASKS} tasks an update) against a fixed loss that grows along one "
            f"identifier (scaled to [0, 1], noise sd {NOISE}), on the spline flow; 20,000 draws "
            "of p0 per estimate.\n\n" + markdown_table(header, rows))
    write_section("adversary_mobility", "How far each step rule lets p_φ move", body,
                  DOCS / "adversary.md")


if __name__ == "__main__":
    main()
