"""Speed of the follower: ``propose(25)`` + ``update`` on those 25 tasks, per flow, one thread.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_adversary.py``. Prints the median milliseconds of
``propose`` (a draw from p_φ), of the update (surrogate with 256 fresh p0 samples, backward,
clipped Adam step, and the new p_φ's log-density at the batch's tasks, which checks it), and of
both, on the sinusoid box with a toy loss, for the spline flow at its
default size (one coupling on this 2-D box), smaller and with two layers, and for the planar
flows; then the default spline and planar flows with ``risk.ar.compile=true`` (timed after their
warm-up iterations, which compile).
"""

from __future__ import annotations

import math
import statistics
import time

import torch

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.allocator import keep_freed_memory
from armeta_rl.risk.adversarial import AdversarialPrinciple
from armeta_rl.tasks import BoxUniform, TaskSpace

TASKS, WARMUP, REPEATS = 25, 10, 200
FLOWS = {
    "spline": {},
    "spline (blocks=1)": {"blocks": 1},
    "spline (layers=2)": {"layers": 2},
    "planar": {},
    "planar (leaky_relu)": {"activation": "leaky_relu"},
}
COMPILED = ("spline", "planar")
"""Flows also timed with ``risk.ar.compile=true`` (inductor; the first iterations compile)."""


def time_iterations(
    principle: AdversarialPrinciple, corner: torch.Tensor
) -> tuple[float, float, float]:
    """Median milliseconds of ``propose``, of ``update`` and of both over ``REPEATS`` follower
    steps."""
    propose_ms, update_ms = [], []
    for step in range(WARMUP + REPEATS):
        start = time.perf_counter()
        tasks = principle.propose(TASKS)
        middle = time.perf_counter()
        principle.update(tasks, (tasks["params"] - corner).pow(2).sum(-1))
        end = time.perf_counter()
        if step >= WARMUP:
            propose_ms.append((middle - start) * 1e3)
            update_ms.append((end - middle) * 1e3)
    total_ms = [p + u for p, u in zip(propose_ms, update_ms, strict=True)]
    return tuple(statistics.median(ms) for ms in (propose_ms, update_ms, total_ms))


def main() -> None:
    keep_freed_memory()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    space = TaskSpace(["amplitude", "phase"], [0.1, 0.0], [5.0, math.pi])
    corner = torch.tensor([0.1, 0.0])
    print(f"{'flow':<22}{'params':>8}{'propose ms':>12}{'update ms':>12}{'total ms':>12}")
    rows = [(name, options, False) for name, options in FLOWS.items()]
    rows += [(name, FLOWS[name], True) for name in COMPILED]
    for name, options, compiled in rows:
        kind = name.split()[0]
        adversary = FlowAdversary(space, BoxUniform(space), kind, **options)
        principle = AdversarialPrinciple(adversary, lr=1e-2, compile=compiled)
        propose, update, total = time_iterations(principle, corner)
        size = sum(p.numel() for p in principle.parameters())
        label = f"{name}, compiled" if compiled else name
        print(f"{label:<22}{size:>8}{propose:>12.2f}{update:>12.2f}{total:>12.2f}")


if __name__ == "__main__":
    main()
