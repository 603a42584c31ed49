"""Throughput of the Ant goal-position env (issue "Ant goal-position meta-RL on MuJoCo").

Env steps per second (one env step = ``frame_skip`` = 5 physics steps) of

* a bare ``mujoco.mj_step(model, data, nstep=5)`` loop over one MjData per simulation (the
  reference: no observation, reward, contact forces or TorchRL);
* gymnasium's ``Ant-v5`` (one env, ``step`` with random actions, reset when it ends);
* the native :class:`mujoco.batch.Batch` step that ``AntGoalEnv`` uses, alone;
* ``AntGoalEnv.rollout`` in one process (random actions, automatic resets);
* ``AntGoalEnv`` split over 2 worker processes (``make_task_split_env``: a ``ParallelEnv`` seen as
  one ``[tasks, episodes]`` env);
* a whole episode collection with the Gaussian MLP policy (``TaskSplitEpisodeCollector.collect``,
  what training runs): in one process with one MuJoCo thread per core, and with the tasks split
  over 2 worker processes of one thread each.

Single-threaded torch; the machine's load average is printed with the table. A meta-iteration of
these collectors (and of Ray's) is timed in turns by the ``bench_ant_ray`` comparison
(``python -m benchmarks.timing bench_ant_ray``).

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_ant_goal.py``; it prints its table and writes it
to its section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from functools import partial

import gymnasium
import mujoco
import numpy as np
import torch
from tensordict import TensorDict
from timing import markdown_table, median_s, write_section

from armeta_rl.collectors.parallel_episodes import TaskSplitEpisodeCollector, make_task_split_env
from armeta_rl.envs.ant_goal import (
    AntGoalEnv,
    load_ant_model,
    observation_size,
)
from armeta_rl.rl.policy import GaussianMLP

STAGE_ACC = mujoco.mjtStage.mjSTAGE_ACC.value


def bare_loop(n_sims: int, steps: int, frame_skip: int) -> Callable[[], None]:
    model = load_ant_model(with_force_sensor=False)
    datas = [mujoco.MjData(model) for _ in range(n_sims)]
    rng = np.random.default_rng(0)
    for data in datas:
        data.ctrl[:] = rng.uniform(-1, 1, model.nu)

    def run() -> None:
        for _ in range(steps):
            for data in datas:
                mujoco.mj_step(model, data, nstep=frame_skip)

    return run


def gymnasium_loop(steps: int) -> Callable[[], None]:
    env = gymnasium.make("Ant-v5")
    env.reset(seed=0)
    env.action_space.seed(0)

    def run() -> None:
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()

    return run


def native_batch(n_sims: int, steps: int, frame_skip: int) -> Callable[[], None]:
    batch = mujoco.batch.Batch(load_ant_model(), n_sims, nthread=1)
    batch.reset()
    ctrl = batch.bind("ctrl")
    ctrl[:] = np.random.default_rng(0).uniform(-1, 1, ctrl.shape)

    def run() -> None:
        for _ in range(steps):
            batch.step(nstep=frame_skip, stage=STAGE_ACC)

    return run


def env_rollout(env, steps: int) -> Callable[[], None]:
    shape = env.batch_size
    goals = 6 * torch.rand(*shape, 2) - 3
    start = env.reset(TensorDict({"params": goals}, shape))
    return lambda: env.rollout(
        steps, tensordict=start.clone(), auto_reset=False, break_when_any_done=False
    )


def task_split_collector(
    workers: int, episodes: int, horizon: int
) -> TaskSplitEpisodeCollector:
    """ant_goal's collector: 1 process with one MuJoCo thread per core, or ``workers`` processes
    with one MuJoCo thread each."""
    threads = None if workers == 1 else 1
    make_env = partial(AntGoalEnv, seed=0, threads=threads)
    return TaskSplitEpisodeCollector(make_env, episodes, horizon, workers=workers)


def collection(collector: TaskSplitEpisodeCollector, tasks: int) -> Callable[[], object]:
    """One ``collect`` of ``tasks`` random goals with a fresh Gaussian MLP policy."""
    model = load_ant_model()
    net = GaussianMLP(observation_size(model), model.nu)
    goals = TensorDict({"params": 6 * torch.rand(tasks, 2) - 3}, [tasks])
    return lambda: collector.collect(goals, policy=net)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--tasks", type=int, default=8)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--steps", type=int, default=25, help="env steps per timed call")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    k, e, steps, frame_skip = args.tasks, args.episodes, args.steps, 5
    n = k * e
    rows: list[tuple[str, str, float]] = []

    t = median_s(bare_loop(n, steps, frame_skip), args.repeats)
    rows.append(("bare mj_step loop (reference)", f"{n} MjData", n * steps / t))
    gym_steps = 1000
    t = median_s(gymnasium_loop(gym_steps), args.repeats)
    rows.append(("gymnasium Ant-v5 (one env)", "1", gym_steps / t))
    t = median_s(native_batch(n, steps, frame_skip), args.repeats)
    rows.append(("mujoco.batch step + forward (native)", f"{n} sims", n * steps / t))
    env = AntGoalEnv((k, e), seed=0)
    t = median_s(env_rollout(env, steps), args.repeats)
    rows.append(("AntGoalEnv.rollout, 1 process", f"[{k}, {e}]", n * steps / t))
    cores = os.cpu_count() or 1
    threaded = AntGoalEnv((k, e), seed=0, threads=None)
    t = median_s(env_rollout(threaded, steps), args.repeats)
    rows.append((f"AntGoalEnv.rollout, 1 process, {cores} MuJoCo threads", f"[{k}, {e}]",
                 n * steps / t))
    parallel = make_task_split_env(partial(AntGoalEnv, threads=1), 2, (k, e), steps)
    t = median_s(env_rollout(parallel, steps), args.repeats)
    rows.append(("AntGoalEnv, 2 processes (ParallelEnv)", f"[{k}, {e}]", n * steps / t))
    parallel.close()
    for workers in (1, 2):
        collector = task_split_collector(workers, e, steps)
        t = median_s(collection(collector, k), args.repeats)
        collector.close()
        how = f"1 process, {cores} MuJoCo threads" if workers == 1 else f"{workers} processes"
        rows.append((f"collect with policy, {how}", f"[{k}, {e}]", n * steps / t))

    bare = rows[0][2]
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    body = (f"Env steps per second (one env step = {frame_skip} physics steps; medians of "
            f"{args.repeats} calls of {steps} steps; load average at the end {load}):\n\n"
            + markdown_table(("what", "batch", "env steps/s", "% of bare loop"),
                             [(name, batch, f"{rate:,.0f}", f"{100 * rate / bare:.0f} %")
                              for name, batch, rate in rows]))
    print(body)
    write_section("bench_ant_goal", "Ant goal-position env (bench_ant_goal.py)", body)

if __name__ == "__main__":
    main()
