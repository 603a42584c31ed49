"""The hardest cells of a grid over a benchmark's box, measured on a reference learner (a run at a
seed no experiment's test runs use): the ``hard_cells`` shift of its shift suite
(configs/shift_suites/, docs/meta-rl.md).

Every cell gets ``tasks`` goals drawn uniformly in it, each scored on ``rollouts`` rollouts; the
``cells`` cells with the worst mean score are the shift. It prints the suite entry and writes
``hard_cells_<suite>.md`` (every cell's score) into ``--out``.

    OMP_NUM_THREADS=1 python studies/hard_cells.py --learner <run> --grid 5 5 --cells 3
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import torch
from tensordict import TensorDict

from armeta_rl.devices import forked_rng
from armeta_rl.tasks.protocol import TASK_KEY, per_rollout, repeat_tasks
from armeta_rl.tasks.shifts import make_shift
from armeta_rl.trainers.evaluation import higher_is_better
from armeta_rl.trainers.players import load_players


def cell_scores(run: str, grid: list[int], tasks: int, rollouts: int, chunk: int, seed: int
                ) -> tuple[dict[tuple[int, ...], float], str, str]:
    """Mean score (the benchmark's metric, e.g. return) of the run's learner on every cell, the
    cells' tasks collected ``chunk`` cells at a time; and the run's suite and metric."""
    cfg, players = load_players(run, "learner")
    leader = players.leader
    cells = list(itertools.product(*(range(n) for n in grid)))
    with forked_rng(players.device):
        torch.manual_seed(seed)
        params = torch.cat([make_shift(players.space, "cell", {
            "kind": "cells", "grid": list(grid), "cells": [list(cell)]}).sample(tasks)[TASK_KEY]
            for cell in cells])
    sign = -1.0 if higher_is_better(leader.metric) else 1.0
    scores = []
    for start in range(0, len(cells), chunk):
        block = params[start * tasks:(start + chunk) * tasks]
        with forked_rng(players.device), torch.no_grad():
            torch.manual_seed(seed + 1 + start)
            batch = repeat_tasks(TensorDict({TASK_KEY: block}, [len(block)]), rollouts)
            losses = leader.evaluate(leader.collect(batch, players.eval_collector))
        scores.append(sign * per_rollout(losses, rollouts).double().mean(0))
    per_cell = torch.cat(scores).reshape(len(cells), tasks).mean(1)
    return dict(zip(cells, per_cell.tolist())), cfg.benchmark.shift_suite, leader.metric


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--learner", required=True)
    parser.add_argument("--grid", type=int, nargs="+", required=True)
    parser.add_argument("--cells", type=int, default=3)
    parser.add_argument("--tasks", type=int, default=16)
    parser.add_argument("--rollouts", type=int, default=4)
    parser.add_argument("--chunk", type=int, default=5)
    parser.add_argument("--seed", type=int, default=2468)
    parser.add_argument("--out", type=Path, default=Path("docs/results/shift_suites"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    scores, suite, metric = cell_scores(args.learner, args.grid, args.tasks, args.rollouts,
                                        args.chunk, args.seed)
    worst_first = sorted(scores, key=scores.get, reverse=not higher_is_better(metric))
    hardest = sorted(worst_first[:args.cells])
    entry = (f"hard_cells: {{kind: cells, grid: {list(args.grid)}, "
             f"cells: {[list(c) for c in hardest]}}}")
    lines = [f"# The hardest cells of the {suite} suite's box", "",
             f"`OMP_NUM_THREADS=1 python studies/hard_cells.py --learner {args.learner} "
             f"--grid {' '.join(map(str, args.grid))} --cells {args.cells} --tasks {args.tasks} "
             f"--rollouts {args.rollouts}`: every cell's mean {metric} over {args.tasks} tasks "
             f"× {args.rollouts} rollouts, worst first; the first {args.cells} are the suite's "
             "`hard_cells`:", "", f"    {entry}", "", f"| cell | mean {metric} |", "|---|---|"]
    lines += [f"| {list(cell)} | {scores[cell]:.4g} |" for cell in worst_first]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"hard_cells_{suite}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
