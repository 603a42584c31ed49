"""Environment steps per second of the batched system-identification envs, and the time one
``SysIdCollector.collect`` takes for a meta-batch (16 tasks x 200 transitions), on one thread.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_sysid_envs.py``
"""

from __future__ import annotations

import torch
from tensordict import TensorDict
from timing import wall_times

from armeta_rl.collectors.sysid import SysIdCollector
from armeta_rl.envs.acrobot import AcrobotEnv
from armeta_rl.envs.pendulum import PendulumEnv

TASKS = 16
TRANSITIONS = 200
REPEATS = 5


def _best_seconds(run, repeats: int = REPEATS) -> float:
    return min(wall_times(run, repeats))


def bench_env(env_cls, episodes: int, steps: int) -> float:
    """Steps per second (one step = one transition of one env) of a random-policy rollout."""
    env = env_cls(batch_size=(TASKS, episodes), seed=0)
    params = 0.4 + 1.2 * torch.rand(TASKS, 1, 2).expand(TASKS, episodes, 2)
    reset = TensorDict({"params": params}, batch_size=env.batch_size)

    def run() -> None:
        env.rollout(steps, tensordict=env.reset(reset.clone()), auto_reset=False,
                    break_when_any_done=False)

    return TASKS * episodes * steps / _best_seconds(run)


def bench_collect(env_name: str, episodes: int) -> float:
    """Milliseconds of one ``collect`` of 16 tasks x 200 transitions."""
    collector = SysIdCollector(env_name, n_transitions=TRANSITIONS, episodes=episodes)
    tasks = TensorDict({"params": 0.4 + 1.2 * torch.rand(TASKS, 2)}, batch_size=[TASKS])
    return 1e3 * _best_seconds(lambda: collector.collect(tasks))


def main() -> None:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    print(f"batched envs, random policy, {TASKS} tasks, one thread (best of {REPEATS})")
    print(f"{'env':10s} {'batch':>8s} {'steps':>6s} {'env steps/s':>12s}")
    for env_cls in (PendulumEnv, AcrobotEnv):
        for episodes, steps in ((1, 200), (10, 20), (16, 200)):
            rate = bench_env(env_cls, episodes, steps)
            print(f"{env_cls.__name__:10s} {f'{TASKS}x{episodes}':>8s} {steps:6d} {rate:12,.0f}")
    print()
    print(f"SysIdCollector.collect: {TASKS} tasks x {TRANSITIONS} transitions")
    print(f"{'env':10s} {'episodes':>8s} {'ms/collect':>11s}")
    for env_name in ("pendulum", "acrobot"):
        for episodes in (1, 10, 20):
            print(f"{env_name:10s} {episodes:8d} {bench_collect(env_name, episodes):11.1f}")


if __name__ == "__main__":
    main()
