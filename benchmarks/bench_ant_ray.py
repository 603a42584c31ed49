"""Seconds per MAML-TRPO meta-iteration on Ant goal-position against the number of Ray workers
(issue "Scale: GPUs and distributed collection", item 4).

A meta-iteration (``MAMLTRPOLeader.step``: rollouts before and after the inner step and the TRPO
step) with ``--tasks`` tasks × ``--episodes`` episodes × ``--horizon`` steps (the paper: 40 × 20 ×
200) is timed with

* the single-process collector of ``ant_goal`` (``TaskSplitEpisodeCollector`` with one worker,
  one MuJoCo thread per core), and
* ``RayEpisodeCollector`` with each of ``--workers`` Ray actors (one MuJoCo thread each),

in turns (``timing.in_turns``: local, Ray 1, Ray 2, ..., the first rotating), so that every Ray row
is a ratio to the local collector measured in the same round: the machine's other load affects both
sides of each ratio alike. Times are scaled linearly to the paper's 40 tasks (as
``bench_ant_goal.py``) and to a 500-iteration run. The table, with the command, the date and the
machine, replaces the section between this script's markers in ``docs/scale.md`` and in
``docs/benchmarks.md`` (``timing.write_section``; ``--no-doc`` prints it only).

Ray: ``--address`` as ``benchmark.collector.address`` (none: a Ray instance of this machine in
this process). The actors reserve ``--cpus-per-worker`` CPUs each (default 0, so that the actors of
every worker count stay alive side by side on one machine between turns).

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_ant_ray.py --tasks 4 --workers 1 2``; on a
16-core machine ``--tasks 48 --workers 1 2 4 8 16`` (the worker counts must divide ``--tasks``).
"""

from __future__ import annotations

import argparse
import statistics
from functools import partial
from pathlib import Path

import timing
import torch
from timing import ratio_cell

from armeta_rl.collectors.parallel_episodes import TaskSplitEpisodeCollector
from armeta_rl.collectors.ray_episodes import RayEpisodeCollector, connect_ray
from armeta_rl.envs.ant_goal import AntGoalEnv
from armeta_rl.learners.maml_trpo import MAMLTRPOLeader
from armeta_rl.tasks import BoxUniform, TaskSpace

SCALE_PAGE = Path(__file__).resolve().parents[1] / "docs" / "scale.md"
PAPER_TASKS, RUN_ITERATIONS = 40, 500


def make_leader(collector, seed: int) -> MAMLTRPOLeader:
    """MAML-TRPO sized by ant_goal's env, its network initialised from ``seed``."""
    torch.manual_seed(seed)
    return MAMLTRPOLeader(collector)


def table(names: list[str], times: dict[str, list[float]], tasks: int) -> str:
    """Median seconds, median ratio to the local collector of the same turn, and the paper-size
    and 500-iteration figures."""
    rows = []
    for name in names:
        seconds = statistics.median(times[name])
        scaled = seconds * PAPER_TASKS / tasks
        rows.append((name, f"{seconds:.1f}", ratio_cell(times[name], times[names[0]]),
                     f"{scaled:.0f}", f"{RUN_ITERATIONS * scaled / 3600:.1f} h"))
    return timing.markdown_table(
        ("collector", "s / iteration (median)", "× local (median of turns, range)",
         f"s / iteration at {PAPER_TASKS} tasks", f"{RUN_ITERATIONS} iterations"), rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", type=int, default=PAPER_TASKS, help="meta-batch timed")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--horizon", type=int, default=200)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2],
                        help="Ray worker counts (1 to 16), each dividing --tasks")
    parser.add_argument("--turns", type=int, default=2, help="timed meta-iterations per row")
    parser.add_argument("--address", default=None,
                        help="Ray cluster (none: a Ray instance of this machine)")
    parser.add_argument("--cpus-per-worker", type=float, default=0.0)
    parser.add_argument("--no-doc", action="store_true", help="print the table only")
    args = parser.parse_args()
    for workers in args.workers:
        if not 1 <= workers <= 16 or args.tasks % workers:
            parser.error(f"--workers {workers}: must be in 1..16 and divide --tasks {args.tasks}")
    torch.set_num_threads(1)
    connect_ray(args.address)

    collectors = {"local (1 process, MuJoCo threads: one per core)": TaskSplitEpisodeCollector(
        partial(AntGoalEnv, threads=None), args.episodes, args.horizon)}
    for workers in args.workers:
        collectors[f"Ray, {workers} worker{'s' if workers > 1 else ''}"] = RayEpisodeCollector(
            partial(AntGoalEnv, threads=1), args.episodes, args.horizon, workers=workers,
            address=args.address, cpus_per_worker=args.cpus_per_worker)
    space = TaskSpace(["goal_x", "goal_y"], [-3.0, -3.0], [3.0, 3.0])
    torch.manual_seed(0)
    tasks = BoxUniform(space).sample(args.tasks)
    leaders = {name: make_leader(collector, 0) for name, collector in collectors.items()}
    for leader in leaders.values():  # untimed: starts the actors and builds the envs
        leader.collector.collect(tasks, policy=leader.net)

    def step(leader: MAMLTRPOLeader) -> None:
        leader.step(leader.collect(tasks, create_graph=True),
                    lambda losses: torch.full_like(losses, 1 / args.tasks))

    turns, _ = timing.in_turns({name: partial(step, leader) for name, leader in leaders.items()},
                               1, args.turns, warmup=0)
    times = {name: timing.turn_medians(turns[name]) for name in leaders}
    for collector in collectors.values():
        collector.close()

    body = (f"{args.tasks} tasks × {args.episodes} episodes × {args.horizon} steps, "
            f"{args.turns} turns, scaled linearly to {PAPER_TASKS} tasks.\n\n"
            + table(list(leaders), times, args.tasks))
    print(body)
    if not args.no_doc:
        title = "Ant goal-position with Ray workers (bench_ant_ray.py)"
        for page in (timing.BENCHMARKS_PAGE, SCALE_PAGE):
            timing.write_section("bench_ant_ray", title, body, page)


if __name__ == "__main__":
    main()
