"""Episode collection with the tasks split over worker processes (issue "Ant goal-position
meta-RL on MuJoCo": use every core through several processes, each worker owning a slice of the
tasks).

:class:`TaskSplitEpisodeCollector` is an :class:`~armeta_rl.collectors.episodes.EpisodeCollector`
whose env of batch size ``[K, episodes]`` is ``workers`` copies of the task-conditioned env, each
of batch size ``[K / workers, episodes]`` in its own process (TorchRL ``ParallelEnv``), seen
through a TorchRL ``BatchSizeTransform`` that reshapes ``[workers, K / workers, episodes]`` to
``[K, episodes]`` and back (task ``k`` lives in worker ``k // (K / workers)``). The per-task
policy of the collector (task ``k``'s parameters on row ``k``) therefore runs unchanged in the
main process, and workers exchange only TensorDicts of observations, actions and identifiers, so the
same split maps onto TorchRL's remote collectors later.

Seeding: every ``collect`` reseeds the env from torch's global RNG (as ``EpisodeCollector``);
TorchRL's batched envs seed worker ``w`` with the ``w``-th seed of the chain
``s, seed_generator(s), ...``. The sub-envs are built with a fixed ``seed`` so that building them
draws nothing from the global RNG: the result is a function of ``torch.manual_seed`` and the
worker count, and equals the same split stepped in one process (``in_process=True``, TorchRL
``SerialEnv``) exactly.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.transforms import BatchSizeTransform

from armeta_rl.collectors.episodes import EpisodeCollector
from armeta_rl.devices import CPU
from armeta_rl.envs.task_env import TaskParallelEnv, TaskSerialEnv
from armeta_rl.errors import ConfigError

WORKERS_KEY = "benchmark.collector.workers"


def _reshape(tensordict: TensorDictBase, shape: tuple[int, ...]) -> TensorDictBase:
    return tensordict.reshape(*shape)


def make_task_split_env(
    make_env: Callable[..., EnvBase],
    workers: int,
    batch_size: tuple[int, int],
    max_steps: int,
    seed: int = 0,
    in_process: bool = False,
    mp_start_method: str = "fork",
) -> TransformedEnv:
    """An env of batch size ``batch_size = (K, episodes)`` made of ``workers`` envs
    ``make_env(batch_size=(K // workers, episodes), max_steps=max_steps, seed=seed)``, each in
    its own process (:class:`~armeta_rl.envs.TaskParallelEnv`, one torch thread per worker) or
    all in this process (``in_process``: :class:`~armeta_rl.envs.TaskSerialEnv`, same results);
    a reset the workers' envs would refuse is refused here, the workers alive."""
    tasks, episodes = (int(n) for n in batch_size)
    if int(workers) < 1 or tasks % int(workers):
        raise ConfigError(WORKERS_KEY, workers, f"must be >= 1 and divide the task count {tasks}")
    workers = int(workers)
    make = partial(make_env, batch_size=(tasks // workers, episodes), max_steps=max_steps,
                   seed=seed)
    if in_process:
        split = TaskSerialEnv(workers, make)
    else:
        # one torch thread per worker; this process keeps its own thread count
        split = TaskParallelEnv(workers, make, mp_start_method=mp_start_method, num_sub_threads=1,
                            num_threads=torch.get_num_threads())
    reshape = BatchSizeTransform(reshape_fn=partial(_reshape, shape=(tasks, episodes)))
    reshape.enable_inv_on_reset = True  # reset TensorDicts ("params", "_reset") go to the workers
    return TransformedEnv(split, reshape)


class TaskSplitEpisodeCollector(EpisodeCollector):
    """:class:`EpisodeCollector` whose ``K`` tasks are split over ``workers`` processes.

    Args:
        make_env: builds one worker's env, called as ``make_env(batch_size=(K // workers,
            episodes), max_steps=max_steps, seed=seed)``; a Hydra ``_partial_: true`` node.
        episodes: episodes per task (the paper: 20).
        max_steps: episode length limit.
        workers: worker processes; it must divide every task count collected. With 1, the env is
            built in this process exactly as :class:`EpisodeCollector` builds it.
        seed: seed the sub-envs are built with (every ``collect`` reseeds them from torch's
            global RNG).
        in_process: step the workers' envs one after the other in this process (TorchRL
            ``SerialEnv``): the same results as the processes, for debugging and tests.
        mp_start_method: ``"fork"`` or ``"spawn"`` (``make_env`` must then be picklable).
        device: where the trajectories are returned (the workers' envs step on the CPU).

    Output and seeding as :class:`EpisodeCollector`: ``[K, episodes, max_steps]`` with
    ``"observation"``, ``"action"``, ``"log_prob"``, ``"reward"``, ``"done"``, ``"terminated"``,
    ``"truncated"``, ``"mask"`` and ``"params"``.
    """

    def __init__(
        self,
        make_env: Callable[..., EnvBase],
        episodes: int = 20,
        max_steps: int = 100,
        workers: int = 1,
        seed: int = 0,
        in_process: bool = False,
        mp_start_method: str = "fork",
        device: torch.device = CPU,
    ) -> None:
        if int(workers) < 1:
            raise ConfigError(WORKERS_KEY, workers, "must be >= 1")
        if mp_start_method not in ("fork", "spawn", "forkserver"):
            raise ConfigError("benchmark.collector.mp_start_method", mp_start_method,
                              "one of fork, spawn, forkserver")
        self.workers = int(workers)
        self.worker_env = make_env
        if self.workers > 1:
            make_env = partial(make_task_split_env, make_env, self.workers, seed=seed,
                               in_process=in_process, mp_start_method=mp_start_method)
        super().__init__(make_env, episodes, max_steps, device)

    def probe_env(self) -> EnvBase:
        """One worker's env of batch size ``[1, 1]`` (no processes), to check task boxes on."""
        return self.worker_env(batch_size=(1, 1), max_steps=1)

    def close(self) -> None:
        """Stop the worker processes (they are started again by the next ``collect``)."""
        threads = torch.get_num_threads()
        for env in self._envs.values():
            if not env.is_closed:
                env.close()
        self._envs.clear()
        torch.set_num_threads(threads)  # TorchRL hands the workers' threads back on close
