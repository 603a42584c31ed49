"""Speed of the follower: ``propose(25)`` + ``update`` on those 25 tasks, per flow, one thread.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_adversary.py``. Prints the median milliseconds of
sampling, of the update (surrogate with 256 fresh p0 samples, backward, clipped Adam step, a
density check after the step), and of both, on the sinusoid box with a toy loss.
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

TASKS, WARMUP, REPEATS = 25, 5, 50
FLOWS = {"spline": {}, "planar": {}, "planar (leaky_relu)": {"activation": "leaky_relu"}}


def time_iterations(principle: AdversarialPrinciple, corner: torch.Tensor) -> tuple[float, float]:
    """Median milliseconds of ``propose`` and of ``update`` over ``REPEATS`` follower steps."""
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
    return statistics.median(propose_ms), statistics.median(update_ms)


def main() -> None:
    keep_freed_memory()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    space = TaskSpace(["amplitude", "phase"], [0.1, 0.0], [5.0, math.pi])
    corner = torch.tensor([0.1, 0.0])
    print(f"{'flow':<22}{'params':>8}{'propose ms':>12}{'update ms':>12}{'total ms':>12}")
    for name, options in FLOWS.items():
        kind = name.split()[0]
        adversary = FlowAdversary(space, BoxUniform(space), kind, **options)
        principle = AdversarialPrinciple(adversary, lr=1e-2)
        propose, update = time_iterations(principle, corner)
        size = sum(p.numel() for p in principle.parameters())
        print(f"{name:<22}{size:>8}{propose:>12.2f}{update:>12.2f}{propose + update:>12.2f}")


if __name__ == "__main__":
    main()
