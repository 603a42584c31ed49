"""CPU cost of the canonical meta-RL benchmarks (HalfCheetah-Vel, HalfCheetah-Dir, Ant-Dir,
HalfCheetah-MassVel, Walker2d-MassVel): seconds per meta-iteration on one thread, at MAML's protocol
(40 tasks × 20 episodes × 200 steps, as pytorch-maml-rl's configs) and at smaller sizes, those under
``families`` in ``benchmarks/workloads.yaml``: six for half_cheetah_vel (the benchmark of the
meta-RL experiments), the largest and the smallest for the others (the cost is close to linear in
between).

Every row builds the run as ``armeta-train`` does from the shipped benchmark YAML (one MuJoCo
thread, ``benchmark.collector.make_env.threads=1``; the tasks, episodes and steps of the row) and
times

* one rollout: a ``collect`` of the row's tasks × episodes with the initial policy, the unit the
  iterations are made of;
* a MAML iteration (MAML-TRPO under ERM: a rollout at θ, the inner step, a rollout of the adapted
  policies, the TRPO step); DR-MAML draws, rolls out and steps alike, so it costs the same;
* an AR-MAML iteration: MAML's, plus the adversary's update, which reads the adapted returns at
  θ_{t+1} and so rolls out twice more (``GameTrainer.follower_losses``).

Each is timed ``--repeats`` times (median) after the row's envs are built, in CPU seconds of this
process (``time.process_time``: the work itself, which the other processes of a shared machine
barely change) and in wall seconds (what the run took on the machine as loaded at the time: on
an idle core the two agree). The cost is close to linear in tasks × episodes × steps (the MuJoCo
steps dominate), so an evaluation of ``n`` tasks costs about two rollouts of ``n`` tasks per
distribution scored. The machine's yardstick (``timing.reference_product_ms``) and load average
are printed with the table, which is written after every row (a long run on a loaded machine
keeps the rows it finished).

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_meta_rl_families.py [--benchmarks ...]
[--sizes 40x20x200 10x10x100 ...] [--repeats 1]``; it prints the table and writes it to its
section of docs/benchmarks.md. Each method's meta-iteration against MAML's, in turns, is the
``bench_ar_overhead`` comparison of ``benchmarks/workloads.yaml`` (``python -m benchmarks.timing
bench_ar_overhead``).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

from timing import (
    as_trained,
    markdown_table,
    reference_product_ms,
    trainer_for,
    workloads,
    write_section,
)

from armeta_rl.trainers.game import GameTrainer

SIZES = workloads("families")
"""Each benchmark's sizes, tasks x episodes x steps."""
ITERATIONS = 500


def sized_trainer(benchmark: str, method: str, tasks: int, episodes: int,
                  steps: int, *overrides: str) -> GameTrainer:
    """The run's trainer as armeta-train builds it, at the row's size on one MuJoCo thread, with
    ``overrides``, its envs built."""
    trainer, players = trainer_for(
        f"benchmark={benchmark}", f"method={method}", f"trainer.meta_batch={tasks}",
        f"benchmark.collector.episodes={episodes}", f"benchmark.collector.max_steps={steps}",
        "benchmark.collector.make_env.threads=1", *overrides)
    players.leader.collector.env(tasks)  # built before the timed iterations
    return trainer


def seconds(fn, repeats: int) -> tuple[float, float]:
    """Median CPU seconds of this process and median wall seconds of ``repeats`` calls."""
    cpu, wall = [], []
    for _ in range(repeats):
        start_cpu, start_wall = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - start_cpu)
        wall.append(time.perf_counter() - start_wall)
    return statistics.median(cpu), statistics.median(wall)


def row(benchmark: str, size: str, repeats: int) -> tuple[str, ...]:
    tasks, episodes, steps = (int(n) for n in size.split("x"))
    maml = sized_trainer(benchmark, "maml", tasks, episodes, steps)
    leader = maml.leader
    initial = maml.principle.propose(tasks)
    rollout, _ = seconds(lambda: leader.collector.collect(initial, None, policy=leader.net),
                         repeats)
    maml_cpu, maml_wall = seconds(maml.train_iteration, repeats)
    ar = sized_trainer(benchmark, "ar_maml", tasks, episodes, steps)
    ar_cpu, ar_wall = seconds(ar.train_iteration, repeats)
    hours = ITERATIONS / 3600
    return (benchmark, f"{tasks} × {episodes} × {steps}", f"{rollout:.1f}", f"{maml_cpu:.1f}",
            f"{ar_cpu:.1f}", f"{maml_cpu * hours:.1f}", f"{ar_cpu * hours:.1f}",
            f"{maml_wall:.0f} / {ar_wall:.0f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--benchmarks", nargs="+", default=list(SIZES), choices=SIZES)
    parser.add_argument("--sizes", nargs="+", default=None,
                        help="tasks x episodes x steps per meta-iteration, e.g. 40x20x200 "
                             "(default: the benchmark's under families in workloads.yaml)")
    parser.add_argument("--repeats", type=int, default=1, help="timed iterations per cell")
    args = parser.parse_args()
    as_trained()
    before = reference_product_ms()
    rows = []
    for benchmark in args.benchmarks:
        for size in args.sizes or SIZES[benchmark]:
            rows.append(row(benchmark, size, args.repeats))
            print(" | ".join(rows[-1]), flush=True)
            write(rows, args.repeats, before, reference_product_ms())


def write(rows: list[tuple[str, ...]], repeats: int, before: float, after: float) -> None:
    """Write the table of ``rows`` to the script's section of docs/benchmarks.md."""
    table = markdown_table(
        ("benchmark", "tasks × episodes × steps", "one rollout CPU s",
         "maml (= dr_maml) CPU s", "ar_maml CPU s", f"maml CPU h / {ITERATIONS} it",
         f"ar_maml CPU h / {ITERATIONS} it", "wall s maml / ar_maml"), rows)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    body = (f"CPU seconds per meta-iteration on one torch thread and one MuJoCo thread (median "
            f"of {repeats} after the envs are built), from the shipped benchmark YAMLs at the "
            f"row's size; CPU hours for {ITERATIONS} iterations (training only, no evaluation); "
            f"the wall seconds the same iterations took on the machine as loaded then. Machine "
            f"yardstick (`timing.reference_product_ms`): {before:.2f} ms at the start, "
            f"{after:.2f} ms after the last row; load average then {load}.\n\n{table}")
    print(body)
    write_section("bench_meta_rl_families", "Meta-RL task families (bench_meta_rl_families.py)",
                  body)


if __name__ == "__main__":
    main()
