"""Environment steps per second of the batched system-identification envs, and the time one
``SysIdCollector.collect`` takes for a meta-batch (16 tasks x 200 transitions), on one thread.

The collect rows vary how the 200 transitions of a task are split into episodes: the TorchRL step
costs about the same for any batch, so the time grows with the steps per episode.
Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_sysid_envs.py``; it prints its tables and
writes them to its section of docs/benchmarks.md.
"""

from __future__ import annotations

import inspect
import statistics
import time

import torch
from tensordict import TensorDict
from timing import markdown_table, wall_times, write_section

from armeta_rl.collectors.sysid import SysIdCollector
from armeta_rl.envs.acrobot import AcrobotEnv
from armeta_rl.envs.pendulum import PendulumEnv

TASKS = 16
TRANSITIONS = 200
REPEATS = 21


def _median_and_best(run, repeats: int = REPEATS) -> tuple[float, float]:
    times = wall_times(run, repeats, warmup=3)
    return statistics.median(times), min(times)


def bench_env(env_cls, episodes: int, steps: int) -> float:
    """Steps per second (one step = one transition of one env) of a random-policy rollout."""
    env = env_cls(batch_size=(TASKS, episodes), seed=0)
    params = 0.4 + 1.2 * torch.rand(TASKS, 1, 2).expand(TASKS, episodes, 2)
    reset = TensorDict({"params": params}, batch_size=env.batch_size)

    def run() -> None:
        env.rollout(steps, tensordict=env.reset(reset.clone()), auto_reset=False,
                    break_when_any_done=False)

    return TASKS * episodes * steps / _median_and_best(run, 7)[0]


def bench_collect(env_name: str, episodes: int) -> tuple[float, float, float]:
    """Median wall, best wall and median CPU milliseconds of one ``collect`` of 16 tasks x 200
    transitions."""
    collector = SysIdCollector(env_name, n_transitions=TRANSITIONS, episodes=episodes)
    tasks = TensorDict({"params": 0.4 + 1.2 * torch.rand(TASKS, 2)}, batch_size=[TASKS])
    median, best = _median_and_best(lambda: collector.collect(tasks))
    cpu = statistics.median(wall_times(lambda: collector.collect(tasks), REPEATS,
                                       clock=time.process_time))
    return 1e3 * median, 1e3 * best, 1e3 * cpu


def main() -> None:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    env_rows = []
    for env_cls in (PendulumEnv, AcrobotEnv):
        for episodes, steps in ((1, 200), (10, 20), (20, 10), (16, 200)):
            rate = bench_env(env_cls, episodes, steps)
            env_rows.append((env_cls.__name__, f"{TASKS} × {episodes}", steps, f"{rate:,.0f}"))
    default = inspect.signature(SysIdCollector).parameters["episodes"].default
    collect_rows = []
    for env_name in ("pendulum", "acrobot"):
        for episodes in (1, 10, 20, 40):
            median, best, cpu = bench_collect(env_name, episodes)
            mark = " (default)" if episodes == default else ""
            collect_rows.append((env_name, f"{episodes}{mark}", TRANSITIONS // episodes,
                                 f"{median:.1f}", f"{best:.1f}", f"{cpu:.1f}"))
    body = (f"Batched envs, random policy, {TASKS} tasks (median of 7 rollouts):\n\n"
            + markdown_table(("env", "batch", "steps", "env steps/s"), env_rows)
            + f"\n\nOne ``SysIdCollector.collect`` of {TASKS} tasks × {TRANSITIONS} transitions "
            f"(wall median and best, CPU median, of {REPEATS}):\n\n"
            + markdown_table(("env", "episodes", "steps", "median ms", "best ms", "CPU ms"),
                             collect_rows))
    print(body)
    write_section("bench_sysid_envs", "System-identification envs (bench_sysid_envs.py)", body)

if __name__ == "__main__":
    main()
