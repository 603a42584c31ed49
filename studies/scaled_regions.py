"""Why the paper's scaled regions look easy (docs/meta-rl.md): a point-robot learner scored on the
four corners of the goal box, two of which are the paper's regions whose rewards are scaled by
0.6 and 0.4, with the returns as the paper scores them and with the scale undone (the same tasks
and random streams in the plain env: MAML-TRPO normalizes each task's advantages, so the
trajectories are the same and only the returns differ), beside the best return of each goal
(the full-speed straight path); and where trained AR adversaries put their mass.

    OMP_NUM_THREADS=1 python studies/scaled_regions.py --learner <point_nav run> \\
        --adversaries <ar_maml runs...> --out docs/results/meta_rl_regions
"""

from __future__ import annotations

import argparse
import platform
from datetime import date
from pathlib import Path

import torch

from armeta_rl.collectors.episodes import PointNavigationCollector
from armeta_rl.envs.point_navigation import reference_return
from armeta_rl.reproduce.aggregate import over_seeds
from armeta_rl.tasks.shifts import shift_seed, suite_shifts
from armeta_rl.trainers.evaluation import evaluate_on
from armeta_rl.trainers.players import load_players

CORNERS = ("corner_top_left", "corner_bottom_right", "corner_top_right", "corner_bottom_left")


def corner_returns(run: str, n_tasks: int, rollouts: int) -> list[dict[str, float]]:
    """Per corner: the reward scale, the mean return as scored, with the scale undone, and the
    mean best return with the scale undone."""
    cfg, players = load_players(run, "learner")
    collector = players.eval_collector
    plain = PointNavigationCollector(collector.episodes, collector.max_steps,
                                     squared_distance=collector.squared_distance,
                                     device=players.device)
    shifts = suite_shifts(players.space, cfg.benchmark.shift_suite, cfg.benchmark.name, CORNERS)
    rows = []
    for name, shift in shifts.items():
        seed = shift_seed(cfg.eval.seed, name)
        scored = evaluate_on(players.leader, shift, collector, n_tasks, [0.5], seed,
                             players.device, rollouts)
        undone = evaluate_on(players.leader, shift, plain, n_tasks, [0.5], seed,
                             players.device, rollouts)
        torch.manual_seed(seed)
        goals = shift.sample(n_tasks)["params"]
        best = reference_return(goals, collector.max_steps)
        centre = goals.mean(0)
        scale = float(torch.tensor(scored["per_task"]).sum() / torch.tensor(
            undone["per_task"]).sum())
        rows.append({"corner": name, "centre": centre.tolist(), "scale": scale,
                     "scored": scored["mean"], "scored_se": scored["sem"],
                     "undone": undone["mean"], "undone_se": undone["sem"],
                     "best": float(best.mean()), "regret": float(best.mean()) - undone["mean"]})
    return rows


def adversary_mass(runs: list[str]) -> dict[str, list[float]]:
    """Per corner, the probability each run's p_φ gives it (midpoint quadrature on a 200² grid),
    and p0's."""
    masses: dict[str, list[float]] = {name: [] for name in ("p0", *CORNERS)}
    for run in runs:
        cfg, players = load_players(run, "adversaries")
        grid, cell = players.space.grid(200)
        with torch.no_grad():
            density = players.adversary.log_prob(grid).exp()
        shifts = suite_shifts(players.space, cfg.benchmark.shift_suite, cfg.benchmark.name,
                              CORNERS)
        for name, shift in shifts.items():
            inside = torch.isfinite(shift.log_prob(grid))
            masses[name].append(float((density * inside).sum() * cell))
        masses["p0"] = [float(torch.isfinite(next(iter(shifts.values())).log_prob(grid)).sum()
                              * cell)]
    return masses


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--learner", required=True)
    parser.add_argument("--adversaries", nargs="*", default=[])
    parser.add_argument("--n-tasks", type=int, default=100)
    parser.add_argument("--rollouts", type=int, default=8)
    parser.add_argument("--out", type=Path, default=Path("docs/results/meta_rl_regions"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = corner_returns(args.learner, args.n_tasks, args.rollouts)
    lines = [
        "# The paper's scaled regions against the other corners",
        "",
        f"`OMP_NUM_THREADS=1 python studies/scaled_regions.py --learner {args.learner} "
        f"--adversaries {' '.join(args.adversaries)}`, run on {date.today().isoformat()} "
        f"({platform.machine()}, torch {torch.__version__}). {args.n_tasks} goals per corner "
        f"of the box (0.25 × 0.25), {args.rollouts} rollouts each; the same goals and random "
        "streams in the paper's env and in the plain one (scale undone).",
        "",
        "| corner | reward scale | return as scored | return, scale undone | best return | "
        "regret, scale undone |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['corner']} | {row['scale']:.2f} | {row['scored']:.2f} ± "
            f"{row['scored_se']:.2f} | {row['undone']:.2f} ± {row['undone_se']:.2f} | "
            f"{row['best']:.2f} | {row['regret']:.2f} |")
    lines.append("")
    lines.append("± the standard error over the goals.")
    if args.adversaries:
        masses = adversary_mass(args.adversaries)
        lines += ["", f"Mass of the trained AR adversaries p_φ ({len(args.adversaries)} runs: "
                  f"{', '.join(args.adversaries)}) in each corner, against p0's:", "",
                  "| corner | p0 | p_φ, mean ± std over runs |", "|---|---|---|"]
        for name in CORNERS:
            lines.append(f"| {name} | {masses['p0'][0]:.4f} | "
                         f"{over_seeds(masses[name]).format()} |")
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "scaled_regions.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
