"""Speed of the follower: ``propose(25)`` + ``update`` on those 25 tasks, per flow, one thread.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_adversary.py [--no-compile]``. Prints the
median milliseconds of ``propose`` (a draw from p_φ), of the update (surrogate with 256 fresh p0
samples, backward, clipped Adam step, and the new p_φ's log-density at the batch's tasks, which
checks it), and of both, on the sinusoid box with a toy loss, for the spline flow at its
default size (one coupling on this 2-D box), smaller and with two layers, and for the planar
flows; then the default spline and planar flows with ``risk.ar.compile=true`` (timed after their
warm-up iterations, which compile), and writes the table to its section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import torch
from timing import as_trained, markdown_table, write_section

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.risk.adversarial import AdversarialPrinciple, ArOptions
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
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--no-compile", action="store_true",
                        help="skip the compiled rows (inductor takes minutes to compile them)")
    args = parser.parse_args()
    as_trained()
    space = TaskSpace(["amplitude", "phase"], [0.1, 0.0], [5.0, math.pi])
    corner = torch.tensor([0.1, 0.0])
    rows = [(name, options, False) for name, options in FLOWS.items()]
    rows += [] if args.no_compile else [(name, FLOWS[name], True) for name in COMPILED]
    table = []
    for name, options, compiled in rows:
        kind = name.split()[0]
        adversary = FlowAdversary(space, BoxUniform(space), kind, **options)
        principle = AdversarialPrinciple(adversary, ArOptions(lr=1e-2, compile=compiled))
        propose, update, total = time_iterations(principle, corner)
        size = sum(p.numel() for p in principle.parameters())
        label = f"{name}, compiled" if compiled else name
        table.append((label, size, f"{propose:.2f}", f"{update:.2f}", f"{total:.2f}"))
    body = (f"The follower on the sinusoid box: ``propose({TASKS})`` and ``update`` with a toy "
            f"loss, medians of {REPEATS} steps after {WARMUP} warm-up steps:\n\n"
            + markdown_table(("flow", "parameters", "propose ms", "update ms", "total ms"), table))
    print(body)
    write_section("bench_adversary", "The follower (bench_adversary.py)", body)

if __name__ == "__main__":
    main()
