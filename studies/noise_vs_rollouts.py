"""The evaluation's noise against its cost: how many rollouts R per task (``eval.rollouts``) an
RL evaluation needs before the noise of a task's score stops mattering (docs/meta-rl.md).

Two finished runs of one benchmark (e.g. MAML and AR-MAML) are scored on the same ``n`` tasks of
p0 with ``max_rollouts`` rollouts per task under common random numbers (the same seeds), in
batches of ``chunk`` rollouts. From the rollouts, per R:

- the noise of a task's score (one rollout's standard deviation around its task's mean, pooled
  over tasks, over √R), against the spread of the tasks' true scores;
- how often two tasks are ranked in the right order (the tasks' mean differences at
  ``max_rollouts`` against Gaussian noise of the two scores at R);
- the standard error of the p0 mean over ``n`` tasks, and of the paired difference of the two
  learners (the first minus the second, on the same tasks and streams), with how much the
  rollout noise adds to it over R = ∞;
- the cost: the wall time of ``evaluate_on`` at R, timed in turn with R = 1 (ratio).

It writes ``noise_vs_rollouts.md`` and ``noise_vs_rollouts.png`` into ``--out``. Run:

    OMP_NUM_THREADS=1 python studies/noise_vs_rollouts.py --runs <run A> <run B> \\
        --out docs/results/meta_rl_noise
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import time
from datetime import date
from pathlib import Path

import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from armeta_rl.devices import forked_rng
from armeta_rl.tasks.protocol import per_rollout, repeat_tasks
from armeta_rl.trainers.evaluation import evaluate_on
from armeta_rl.trainers.players import load_players

GRID = (1, 2, 4, 8, 16, 32)


def rollout_scores(run: str, n_tasks: int, max_rollouts: int, chunk: int, seed: int
                   ) -> tuple[torch.Tensor, str, str]:
    """Returns ``[max_rollouts, n_tasks]`` (higher is better) of the run's learner on p0's tasks
    drawn under ``seed``; chunk ``c`` is collected under ``seed + 1 + c`` (the same for every
    run: common random numbers). Also the run's method and metric."""
    cfg, players = load_players(run, "runs")
    leader = players.leader
    with forked_rng(players.device):
        torch.manual_seed(seed)
        tasks = players.initial.sample(n_tasks)
    blocks = []
    for c in range(max_rollouts // chunk):
        with forked_rng(players.device), torch.no_grad():
            torch.manual_seed(seed + 1 + c)
            losses = leader.evaluate(leader.collect(repeat_tasks(tasks, chunk),
                                                    players.eval_collector))
        blocks.append(per_rollout(losses, chunk).double())
    scores = torch.cat(blocks)
    return (-scores if leader.metric == "return" else scores), cfg.method.name, leader.metric


def eval_seconds(run: str, n_tasks: int, rollouts: list[int], repeats: int
                 ) -> dict[int, float]:
    """Median wall seconds of ``evaluate_on`` at each R, the R values timed in turn."""
    cfg, players = load_players(run, "runs")
    times: dict[int, list[float]] = {r: [] for r in rollouts}
    for _ in range(repeats):
        for r in rollouts:
            start = time.perf_counter()
            evaluate_on(players.leader, players.initial, players.eval_collector, n_tasks, [0.5],
                        cfg.eval.seed, players.device, r)
            times[r].append(time.perf_counter() - start)
    return {r: statistics.median(t) for r, t in times.items()}


def components(scores: torch.Tensor) -> tuple[float, float, torch.Tensor]:
    """(within-task variance of one rollout, between-task variance of the true scores, the task
    means) of ``[R, n]`` scores; the between part corrected for the means' own noise."""
    within = float(scores.var(0).mean())
    means = scores.mean(0)
    between = max(float(means.var()) - within / scores.shape[0], 0.0)
    return within, between, means


def ranking_accuracy(means: torch.Tensor, within: float, rollouts: int) -> float:
    """The chance that two tasks' scores at R rollouts order them as their means do, averaged
    over all pairs (Gaussian noise of variance within/R on each score)."""
    gaps = (means[:, None] - means[None, :]).abs()
    pairs = torch.triu_indices(len(means), len(means), 1)
    z = gaps[pairs[0], pairs[1]] / math.sqrt(2 * within / rollouts)
    return float(torch.special.ndtr(z).mean())


def curve(first: torch.Tensor, second: torch.Tensor) -> list[dict[str, float]]:
    """Per R of :data:`GRID` (up to the rollouts measured), the noise figures of the module."""
    n = first.shape[1]
    within, between, means = components(first)
    diff_within, diff_between, _ = components(first - second)
    rows = []
    for r in (r for r in GRID if r <= first.shape[0]):
        paired = math.sqrt((diff_between + diff_within / r) / n)
        rows.append({
            "R": r,
            "noise_sd": math.sqrt(within / r),
            "between_sd": math.sqrt(between),
            "ranking": ranking_accuracy(means, within, r),
            "mean_se": math.sqrt((between + within / r) / n),
            "paired_se": paired,
            "paired_excess": paired / math.sqrt(diff_between / n) - 1 if diff_between > 0
            else math.inf,
        })
    return rows


def write(rows: list[dict[str, float]], seconds: dict[int, float], names: tuple[str, str],
          runs: tuple[str, str], args: argparse.Namespace, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    figure = Figure(figsize=(10, 3.4), layout="constrained")
    FigureCanvasAgg(figure)
    left, middle, right = figure.subplots(1, 3)
    r = [row["R"] for row in rows]
    left.plot(r, [row["noise_sd"] for row in rows], marker="o", label="task score noise")
    left.axhline(rows[0]["between_sd"], color="k", ls="--", lw=0.8, label="spread of tasks")
    left.set_title("noise of a task's score", fontsize=9)
    middle.plot(r, [row["ranking"] for row in rows], marker="o")
    middle.set_title("two tasks ranked right", fontsize=9)
    right.plot(r, [row["paired_se"] for row in rows], marker="o", label=f"{names[0]} − {names[1]}")
    right.plot(r, [row["mean_se"] for row in rows], marker="o", label="p0 mean")
    right.set_title(f"standard error over {args.n_tasks} tasks", fontsize=9)
    right.legend(fontsize=7)
    left.legend(fontsize=7)
    for ax in (left, middle, right):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("rollouts per task R")
    figure.savefig(out / "noise_vs_rollouts.png", dpi=90)
    base = seconds.get(1)
    lines = [
        "# Evaluation noise against rollouts per task",
        "",
        f"`OMP_NUM_THREADS=1 python studies/noise_vs_rollouts.py --runs {runs[0]} {runs[1]} "
        f"--n-tasks {args.n_tasks} --max-rollouts {args.max_rollouts}`, run on "
        f"{date.today().isoformat()} ({platform.machine()}, torch {torch.__version__}, 1 "
        "thread, a machine shared with other jobs).",
        "",
        f"{args.n_tasks} tasks of p0, {args.max_rollouts} rollouts each (a rollout: adaptation "
        "from fresh episodes, then the adapted policy's episodes), the two learners "
        f"({names[0]}, {names[1]}) on the same tasks and random streams. Noise: one rollout's "
        "standard deviation around its task's mean over √R; ranking: the chance two tasks' "
        "scores order them as their means do; paired: the standard error of the mean of "
        f"{names[0]} − {names[1]} over the tasks, and what the rollout noise adds to it over "
        "R = ∞; seconds: `evaluate_on` at R timed in turn with R = 1.",
        "",
        "| R | task score noise (sd) | spread of tasks (sd) | two tasks ranked right | "
        "s.e. of the p0 mean | s.e. of the paired difference | noise's share of it | "
        "seconds (× R = 1) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        cost = seconds.get(row["R"])
        cost_text = "–" if cost is None or base is None else f"{cost:.1f} ({cost / base:.1f}×)"
        lines.append(
            f"| {row['R']} | {row['noise_sd']:.2f} | {row['between_sd']:.2f} | "
            f"{100 * row['ranking']:.1f} % | {row['mean_se']:.3f} | {row['paired_se']:.3f} | "
            f"+{100 * row['paired_excess']:.0f} % | {cost_text} |")
    lines += ["", "![noise against R](noise_vs_rollouts.png)", ""]
    (out / "noise_vs_rollouts.md").write_text("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs=2, required=True, help="two finished runs of a benchmark")
    parser.add_argument("--n-tasks", type=int, default=100)
    parser.add_argument("--max-rollouts", type=int, default=32)
    parser.add_argument("--chunk", type=int, default=8)
    parser.add_argument("--seed", type=int, default=4321)
    parser.add_argument("--timing", type=int, nargs="*", default=[1, 2, 4, 8])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("docs/results/meta_rl_noise"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    first, name_a, _ = rollout_scores(args.runs[0], args.n_tasks, args.max_rollouts, args.chunk,
                                      args.seed)
    second, name_b, _ = rollout_scores(args.runs[1], args.n_tasks, args.max_rollouts,
                                       args.chunk, args.seed)
    seconds = eval_seconds(args.runs[0], args.n_tasks, args.timing, args.repeats)
    rows = curve(first, second)
    write(rows, seconds, (name_a, name_b), tuple(args.runs), args, args.out)
    print((args.out / "noise_vs_rollouts.md").read_text())


if __name__ == "__main__":
    main()
