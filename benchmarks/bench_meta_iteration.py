"""Milliseconds per meta-iteration of the regression and system-identification games, one thread:
the ``bench_meta_iteration`` comparison under ``turns`` in ``benchmarks/workloads.yaml``
(``timing.compare_in_turns``).

Rows: the full AR-MAML iteration (data collection, leader step, follower losses at θ_{t+1},
adversary update every iteration) with the spline and the planar adversary, and plain MAML with
either batched adaptation (``learner.maml.adaptation``), on sinusoid_uniform (25 tasks),
pendulum_uniform and acrobot_uniform (16 tasks × 200 transitions, collection included); and the
sinusoid's second-order meta-gradient computed with a Python loop over tasks instead of ``vmap``
(:func:`looped_meta_gradient`). ``--compile`` adds rows with the adversary's flow and/or the
leader's loss compiled. Config overrides may follow on the command line.

The rows of a benchmark take turns: a shared machine runs slower for spells of tens of seconds
(up to 1.5x here); timed one after the other, one row could fall in such a spell and the next one
not. Short turns of consecutive iterations keep each trainer's data warm in the caches, as in a
real run.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_meta_iteration.py [--compile] [--rounds 10]
[--benchmarks sinusoid_uniform ...]``; it writes its table to its section of docs/benchmarks.md.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from timing import compare_in_turns

from armeta_rl.trainers.game import GameTrainer


def looped_meta_gradient(trainer: GameTrainer) -> Callable[[], None]:
    """The same meta-gradient with a Python loop over tasks (the pattern vmap replaces)."""
    leader = trainer.leader
    params = dict(leader.model.named_parameters())

    def step() -> None:
        tasks = trainer.principle.propose(trainer.meta_batch)
        data = leader.collect(tasks)
        support, query = data["support"], data["query"]
        losses = torch.stack([
            leader.query_loss(params, support["x"][k], support["y"][k], query["x"][k],
                              query["y"][k])
            for k in range(len(data))
        ])
        leader.optimizer.zero_grad()
        losses.mean().backward()
        leader.optimizer.step()

    return step


if __name__ == "__main__":
    compare_in_turns("bench_meta_iteration", wraps={"looped_meta_gradient": looped_meta_gradient})
