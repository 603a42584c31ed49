"""Environment steps per second of the batched system-identification envs, and the time one
``SysIdCollector.collect`` takes for a meta-batch (16 tasks x 200 transitions), on one thread.

The collect rows vary how the 200 transitions of a task are split into episodes: the TorchRL step
costs about the same for any batch, so the time grows with the steps per episode.
Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_sysid_envs.py``
"""

from __future__ import annotations

import inspect
import statistics
import time

import torch
from tensordict import TensorDict
from timing import wall_times

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
    print(f"batched envs, random policy, {TASKS} tasks, one thread (median of 7)")
    print(f"{'env':10s} {'batch':>8s} {'steps':>6s} {'env steps/s':>12s}")
    for env_cls in (PendulumEnv, AcrobotEnv):
        for episodes, steps in ((1, 200), (10, 20), (20, 10), (16, 200)):
            rate = bench_env(env_cls, episodes, steps)
            print(f"{env_cls.__name__:10s} {f'{TASKS}x{episodes}':>8s} {steps:6d} {rate:12,.0f}")
    print()
    default = inspect.signature(SysIdCollector).parameters["episodes"].default
    print(f"SysIdCollector.collect: {TASKS} tasks x {TRANSITIONS} transitions "
          f"(wall median and best, CPU median, of {REPEATS}; * = default)")
    print(f"{'env':10s} {'episodes':>9s} {'steps':>6s} {'median ms':>10s} {'best ms':>8s} "
          f"{'CPU ms':>7s}")
    for env_name in ("pendulum", "acrobot"):
        for episodes in (1, 10, 20, 40):
            median, best, cpu = bench_collect(env_name, episodes)
            mark = "*" if episodes == default else " "
            print(f"{env_name:10s} {episodes:8d}{mark} {TRANSITIONS // episodes:6d} "
                  f"{median:10.1f} {best:8.1f} {cpu:7.1f}")


if __name__ == "__main__":
    main()
