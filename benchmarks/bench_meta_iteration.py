"""Milliseconds per meta-iteration of the regression and system-identification games, one thread.

Rows: the full AR-MAML iteration (data collection, leader step, follower losses at θ_{t+1},
adversary update every iteration) with the spline and the planar adversary, and plain MAML, on
sinusoid_uniform (25 tasks), pendulum_uniform and acrobot_uniform (16 tasks × 200 transitions,
collection included); and the sinusoid's second-order meta-gradient computed with a Python loop
over tasks instead of ``vmap``. Config overrides may follow on the command line.
Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_meta_iteration.py``.
"""

from __future__ import annotations

import statistics
import sys
from collections.abc import Callable

import torch
from hydra import compose, initialize_config_dir
from timing import wall_times

from armeta_rl.allocator import keep_freed_memory
from armeta_rl.cli import config_dir
from armeta_rl.trainers.game import GameTrainer
from armeta_rl.trainers.runs import build_players


def milliseconds(fn: Callable[[], object], repeats: int, warmup: int) -> tuple[float, float]:
    """Median and interquartile range of ``fn``'s wall time in ms."""
    q1, median, q3 = statistics.quantiles([1000 * t for t in wall_times(fn, repeats, warmup)], n=4)
    return median, q3 - q1


def trainer_for(method: str, *overrides: str) -> GameTrainer:
    """A trainer for ``method`` on the default benchmark with config ``overrides``."""
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        cfg = compose("train", overrides=[f"method={method}", *overrides])
    players = build_players(cfg)
    return GameTrainer(
        players.leader,
        players.principle,
        iterations=10**9,
        meta_batch=cfg.trainer.meta_batch,
        progress=False,
    )


def looped_meta_gradient(trainer: GameTrainer) -> Callable[[], None]:
    """The same meta-gradient with a Python loop over tasks (the pattern vmap replaces)."""
    leader = trainer.leader
    params = dict(leader.model.named_parameters())

    def step() -> None:
        tasks = trainer.principle.propose(trainer.meta_batch)
        data = leader.collector.collect(tasks)
        losses = torch.stack([leader._adapted_loss(params, data[k]) for k in range(len(data))])
        leader.optimizer.zero_grad()
        losses.mean().backward()
        leader.optimizer.step()

    return step


def main(extra: list[str]) -> None:
    """Print the table; ``extra`` are config overrides (e.g. ``risk.ar.lam=0.1``)."""
    keep_freed_memory()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    rows = []
    for benchmark in ("sinusoid_uniform", "pendulum_uniform", "acrobot_uniform"):
        for label, method, flow in [
            ("ar_maml, spline adversary", "ar_maml", "spline"),
            ("ar_maml, planar adversary", "ar_maml", "planar"),
            ("maml (ERM)", "maml", "spline"),
        ]:
            trainer = trainer_for(method, f"benchmark={benchmark}", f"risk.ar.flow={flow}", *extra)
            rows.append((benchmark, label, *milliseconds(trainer.train_iteration, 100, 10)))
    trainer = trainer_for("maml", *extra)
    looped = milliseconds(looped_meta_gradient(trainer), 50, 5)
    rows.append(("sinusoid_uniform", "maml, per-task Python loop", *looped))
    print(f"meta-iteration time, {torch.get_num_threads()} thread, second-order MAML")
    print("| benchmark | meta-iteration | median ms | IQR ms |\n|---|---|---|---|")
    for benchmark, label, median, iqr in rows:
        print(f"| {benchmark} | {label} | {median:.1f} | {iqr:.1f} |")


if __name__ == "__main__":
    main(sys.argv[1:])
