"""What a follower loses by reading the step's losses at θ_t instead of fresh ones at θ_{t+1}
(``trainer.follower_at=step`` against ``next``, docs/meta-rl.md).

From a finished meta-RL run's learner, ``--steps`` leader steps are taken on ``--tasks`` tasks of
p0 each; per step, the tasks' losses are read three ways: the step's own at θ_t (what ``step``
hands the follower), fresh at θ_{t+1} (what ``next`` collects) and fresh at θ_{t+1} again under
another random stream (a second draw of the same quantity). The follower's gradient reads the
losses centred over the batch (its baseline), so the table compares centred losses: the
correlation of the step's with the fresh ones against the correlation of two fresh draws, and the
root-mean-square of their differences. Where the first pair agrees as well as the second, the
step moved the tasks' losses by less than a rollout's noise, and ``step`` gives the follower the
signal ``next`` would, at no cost.

Run: ``OMP_NUM_THREADS=1 python studies/follower_lag.py --run <run dir> [--tasks 20]
[--steps 10]``; it prints the table and writes it to its section of docs/meta-rl.md.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from pathlib import Path

import torch

from armeta_rl.devices import forked_rng
from armeta_rl.learners.base import weighted_sum
from armeta_rl.risk.erm import uniform_weights
from armeta_rl.trainers.players import load_players

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from timing import DOCS, markdown_table, write_section  # noqa: E402 (the benchmarks' writer)


def centred(losses: torch.Tensor) -> torch.Tensor:
    return (losses - losses.mean()).double()


def correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a * b).sum() / (a.norm() * b.norm()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True, help="a finished meta-RL run directory")
    parser.add_argument("--tasks", type=int, default=20)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    _, players = load_players(args.run, "run")
    leader = players.leader
    rows, lag, noise = [], [], []
    for step in range(args.steps):
        with forked_rng(players.device):
            torch.manual_seed(args.seed + 3 * step)
            tasks = players.initial.sample(args.tasks)
            out, _ = leader.step(leader.collect(tasks, create_graph=True),
                                 lambda losses: uniform_weights(losses))
            fresh = []
            for draw in (1, 2):
                torch.manual_seed(args.seed + 3 * step + draw)
                with torch.no_grad():
                    fresh.append(leader.evaluate(leader.collect(tasks)))
        now, first, second = centred(out["loss"]), centred(fresh[0]), centred(fresh[1])
        lag.append(correlation(now, first))
        noise.append(correlation(second, first))
        rows.append((step + 1, f"{lag[-1]:.3f}", f"{noise[-1]:.3f}",
                     f"{math.sqrt(float((now - first).square().mean())):.2f}",
                     f"{math.sqrt(float((second - first).square().mean())):.2f}",
                     f"{float(weighted_sum(uniform_weights(out['loss']), out['loss'])):.1f}"))
    rows.append(("median", f"{statistics.median(lag):.3f}", f"{statistics.median(noise):.3f}",
                 "", "", ""))
    table = markdown_table(("leader step", "corr(θ_t step, θ_{t+1} fresh)",
                            "corr(θ_{t+1} fresh, θ_{t+1} fresh again)",
                            "RMS difference, step − fresh", "RMS difference, fresh − fresh",
                            "mean loss at θ_t"), rows)
    body = (f"Learner: `{args.run}`; {args.tasks} tasks of p0 per step, losses centred over the "
            f"batch (the follower's baseline).\n\n{table}")
    print(body)
    write_section("follower_lag", "The follower's losses at θ_t and at θ_{t+1} "
                  "(studies/follower_lag.py)", body, page=DOCS / "meta-rl.md")


if __name__ == "__main__":
    main()
