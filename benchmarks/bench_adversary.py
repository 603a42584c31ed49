"""Speed of the follower: ``propose(25)`` + ``update`` on those 25 tasks, per flow, one thread.

Each row of ``adversary`` in ``benchmarks/workloads.yaml`` is config overrides of AR-MAML on
the sinusoid (its flow and the flow's arguments; the principle built as ``armeta-train`` builds
it, ``timing.trainer_for``). Prints the median milliseconds of ``propose`` (a draw from p_φ), of
the update (surrogate with fresh p0 samples, backward, clipped Adam step, and the new p_φ's
log-density at the batch's tasks, which checks it), and of both, with a toy loss; the rows that
compile (``risk.ar.compile=true``) are timed after their warm-up steps, which compile, and skipped
with ``--no-compile``. Writes the table to its section of docs/benchmarks.md.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_adversary.py [--no-compile]``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from timing import as_trained, markdown_table, trainer_for, workloads, write_section

from armeta_rl.risk.adversarial import AdversarialPrinciple
from armeta_rl.tasks import TASK_KEY

TASKS, WARMUP, REPEATS = 25, 10, 200


def time_iterations(principle: AdversarialPrinciple) -> tuple[float, ...]:
    """Median milliseconds of ``propose``, of ``update`` and of both over ``REPEATS`` follower
    steps on the toy loss (squared distance to the box's lower corner)."""
    corner = torch.tensor(principle.initial.space.low)
    propose_ms, update_ms = [], []
    for step in range(WARMUP + REPEATS):
        start = time.perf_counter()
        tasks = principle.propose(TASKS)
        middle = time.perf_counter()
        principle.update(tasks, (tasks[TASK_KEY] - corner).pow(2).sum(-1))
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
    table = []
    for label, overrides in workloads("adversary").items():
        if args.no_compile and "risk.ar.compile=true" in overrides:
            continue
        _, players = trainer_for("benchmark=sinusoid_uniform", "method=ar_maml", *overrides)
        principle = players.principle
        size = sum(p.numel() for p in principle.parameters())
        table.append((label, size, *(f"{ms:.2f}" for ms in time_iterations(principle))))
    body = (f"The follower on the sinusoid box: ``propose({TASKS})`` and ``update`` with a toy "
            f"loss, medians of {REPEATS} steps after {WARMUP} warm-up steps:\n\n"
            + markdown_table(("flow", "parameters", "propose ms", "update ms", "total ms"), table))
    print(body)
    write_section("bench_adversary", "The follower (bench_adversary.py)", body)


if __name__ == "__main__":
    main()
