"""Environment steps per second of the batched system-identification envs, through TorchRL's
``env.rollout`` and through ``env.transitions`` (the same transitions bit for bit, without
TorchRL's per-step machinery: what ``SysIdCollector`` steps with), and the time one
``SysIdCollector.collect`` takes for a meta-batch (16 tasks x 200 transitions), on one thread.

The collect rows vary how the 200 transitions of a task are split into episodes: a step costs
about the same for any batch, so the time grows with the steps per episode. The env rows are CPU
time (``time.process_time``), which other processes on a shared machine stretch less than wall
time.

The physics rows time one step of the equations of motion alone (``env._dynamics``, the step
that ``transitions`` chains; 16 tasks × 1 episode, the paper protocol's batch), eagerly and
through ``torch.compile`` with an empty compile cache (the first call's seconds are the compile),
as ``benchmark.collector.compile=true`` compiles it. The paper protocol chains 200 such steps a
meta-iteration, one after the other, so 200 × a step bounds how fast its collection can get in
either form (docs/speed-options.md).

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_sysid_envs.py``; it prints its tables and
writes them to its section of docs/benchmarks.md.
"""

from __future__ import annotations

import inspect
import os
import statistics
import tempfile
import time

import torch
from tensordict import TensorDict
from timing import markdown_table, wall_times, write_section

from armeta_rl.collectors.sysid import SysIdCollector
from armeta_rl.compiling import maybe_compile
from armeta_rl.envs.acrobot import AcrobotEnv
from armeta_rl.envs.pendulum import PendulumEnv

TASKS = 16
TRANSITIONS = 200
REPEATS = 21


def _median_and_best(run, repeats: int = REPEATS) -> tuple[float, float]:
    times = wall_times(run, repeats, warmup=3)
    return statistics.median(times), min(times)


def bench_env(env_cls, episodes: int, steps: int) -> tuple[float, float]:
    """Steps per second of CPU time (one step = one transition of one env) of a random-policy
    rollout through ``env.rollout`` and through ``env.transitions``."""
    env = env_cls(batch_size=(TASKS, episodes), seed=0)
    params = 0.4 + 1.2 * torch.rand(TASKS, 1, 2).expand(TASKS, episodes, 2)
    reset = TensorDict({"params": params}, batch_size=env.batch_size)

    def rollout() -> None:
        env.rollout(steps, tensordict=env.reset(reset.clone()), auto_reset=False,
                    break_when_any_done=False)

    def transitions() -> None:
        env.reset(reset.clone())
        env.transitions(steps)

    rates = []
    for run in (rollout, transitions):
        seconds = statistics.median(wall_times(run, 7, warmup=3, clock=time.process_time))
        rates.append(TASKS * episodes * steps / seconds)
    return rates[0], rates[1]


def bench_collect(env_name: str, episodes: int) -> tuple[float, float, float]:
    """Median wall, best wall and median CPU milliseconds of one ``collect`` of 16 tasks x 200
    transitions."""
    collector = SysIdCollector(env_name, n_transitions=TRANSITIONS, episodes=episodes)
    tasks = TensorDict({"params": 0.4 + 1.2 * torch.rand(TASKS, 2)}, batch_size=[TASKS])
    median, best = _median_and_best(lambda: collector.collect(tasks))
    cpu = statistics.median(wall_times(lambda: collector.collect(tasks), REPEATS,
                                       clock=time.process_time))
    return 1e3 * median, 1e3 * best, 1e3 * cpu


def bench_physics(env_cls) -> tuple[float, float, float, float]:
    """Microseconds of one eager and one compiled physics step (CPU time, median of 2,000 after
    200 untimed), the compiled form's first call in seconds (its compile, with an empty cache)
    and the largest deviation of the compiled step from the eager one."""
    env = env_cls(batch_size=(TASKS, 1), seed=0)
    env.reset(TensorDict({"params": 0.4 + 1.2 * torch.rand(TASKS, 1, 2)},
                         batch_size=env.batch_size))
    state = env._state.clone()
    action = env._random_actions(1)[0]
    eager = env._dynamics
    compiled = maybe_compile(env._dynamics, "inductor")  # what compile_dynamics=True runs
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = tempfile.mkdtemp(prefix="bench_sysid_inductor_")
    start = time.perf_counter()
    compiled(state.clone(), action)
    compile_seconds = time.perf_counter() - start
    deviation = float((compiled(state.clone(), action) - eager(state.clone(), action)).abs().max())
    step_us = [1e6 * statistics.median(wall_times(lambda f=f: f(state.clone(), action), 2000,
                                                  warmup=200, clock=time.process_time))
               for f in (eager, compiled)]
    return step_us[0], step_us[1], compile_seconds, deviation


def main() -> None:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    env_rows = []
    for env_cls in (PendulumEnv, AcrobotEnv):
        for episodes, steps in ((1, 200), (10, 20), (20, 10), (16, 200)):
            slow, fast = bench_env(env_cls, episodes, steps)
            env_rows.append((env_cls.__name__, f"{TASKS} × {episodes}", steps, f"{slow:,.0f}",
                             f"{fast:,.0f}", f"{fast / slow:.1f}×"))
    default = inspect.signature(SysIdCollector).parameters["episodes"].default
    collect_rows = []
    for env_name in ("pendulum", "acrobot"):
        for episodes in (1, 10, 20, 40):
            median, best, cpu = bench_collect(env_name, episodes)
            mark = " (default)" if episodes == default else ""
            collect_rows.append((env_name, f"{episodes}{mark}", TRANSITIONS // episodes,
                                 f"{median:.1f}", f"{best:.1f}", f"{cpu:.1f}"))
    physics_rows = []
    for env_cls in (PendulumEnv, AcrobotEnv):
        eager, compiled, compile_seconds, deviation = bench_physics(env_cls)
        physics_rows.append((env_cls.__name__, f"{eager:.1f}", f"{compiled:.1f}",
                             f"{eager / compiled:.1f}×", f"{TRANSITIONS * eager / 1e3:.1f}",
                             f"{TRANSITIONS * compiled / 1e3:.1f}", f"{compile_seconds:.1f}",
                             f"{deviation:.1e}"))
    body = (f"Batched envs, random policy, {TASKS} tasks (env steps per second of CPU time, "
            f"median of 7 rollouts, each with its reset):\n\n"
            + markdown_table(("env", "batch", "steps", "env.rollout", "env.transitions",
                              "transitions / rollout"), env_rows)
            + f"\n\nOne ``SysIdCollector.collect`` of {TASKS} tasks × {TRANSITIONS} transitions "
            f"(wall median and best, CPU median, of {REPEATS}):\n\n"
            + markdown_table(("env", "episodes", "steps", "median ms", "best ms", "CPU ms"),
                             collect_rows)
            + f"\n\nOne physics step (``env._dynamics``) of {TASKS} × 1 envs, eager and compiled "
            f"(``torch.compile``, empty cache; µs of CPU time, median of 2,000; the first "
            f"row's compile includes starting torch's compiler in the process), and "
            f"{TRANSITIONS} such steps in a row, as the paper protocol's collection chains "
            "them:\n\n"
            + markdown_table(("env", "eager µs", "compiled µs", "eager / compiled",
                              f"{TRANSITIONS} eager steps ms", f"{TRANSITIONS} compiled steps ms",
                              "compile s", "largest deviation"), physics_rows))
    print(body)
    write_section("bench_sysid_envs", "System-identification envs (bench_sysid_envs.py)", body)


if __name__ == "__main__":
    main()
