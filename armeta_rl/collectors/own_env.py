"""Bring your own env: a TorchRL env that runs one task per instance, taken under
:data:`~armeta_rl.tasks.TASK_KEY` at reset, meta-trained by the package's learners and adversary
with no ``[tasks, episodes]`` env written.

:func:`one_task_envs` builds the ``[tasks, episodes]`` env the episode collectors step from
instances of the user's env: a :class:`~armeta_rl.envs.TaskSerialEnv` (or, with ``parallel``, a
:class:`~armeta_rl.envs.TaskParallelEnv`: one process per instance) of them, each seen through a
:class:`TaskBox` that declares the benchmark's box (so the batched env tells it and checks every
reset against it in the calling process) and cut to episodes of ``max_steps`` by a
``StepCounter``, reshaped to ``[tasks, episodes]`` by TorchRL's ``BatchSizeTransform``. An
instance of batch size ``b`` runs ``prod(b)`` episodes of its one task; the episodes per task
must be a multiple of that. :class:`OneTaskEnvCollector` is the episode collector over it, what a
benchmark YAML names (docs/own-env.md).

The user's env must read its task under ``"params"`` (a float tensor ``[*b, d]``) at reset,
declare it in its state spec (so TorchRL's wrappers forward it), keep it across automatic
resets, emit a flat ``"observation"`` and declare a continuous action spec.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from functools import partial
from typing import Any

import torch
from torchrl.envs import Compose, EnvBase, StepCounter, Transform
from torchrl.envs.transforms import BatchSizeTransform

from armeta_rl.collectors.episodes import EpisodeCollector
from armeta_rl.devices import CPU
from armeta_rl.envs.task_env import TaskParallelEnv, TaskSerialEnv, TaskTransformedEnv
from armeta_rl.errors import ConfigError
from armeta_rl.tasks.protocol import IdentifierCheck
from armeta_rl.tasks.space import TaskSpace

EPISODES_KEY = "benchmark.collector.episodes"


class TaskBox(Transform):
    """Declares the task box of an env that takes identifiers under ``"params"`` but tells none
    (a user's env): the env then tells ``space`` (:func:`~armeta_rl.envs.task_space`), and a
    batched env of it (:class:`~armeta_rl.envs.TaskSerialEnv`,
    :class:`~armeta_rl.envs.TaskParallelEnv`) checks every reset against it in the calling
    process (every identifier finite and in the box). It changes no data.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors.own_env import TaskBox
        >>> from armeta_rl.envs import TaskSerialEnv, TaskTransformedEnv, identifier_check
        >>> from armeta_rl.envs.tutorial_pendulum import TutorialPendulumEnv
        >>> from armeta_rl.tasks import TaskSpace
        >>> identifier_check(TutorialPendulumEnv()) is None  # a user's env tells no box
        True
        >>> box = TaskSpace(["m", "l"], low=[0.5, 0.5], high=[1.5, 1.5])
        >>> env = TaskSerialEnv(2, lambda: TaskTransformedEnv(TutorialPendulumEnv(), TaskBox(box)))
        >>> env.task_space
        TaskSpace(names=('m', 'l'), low=(0.5, 0.5), high=(1.5, 1.5))
        >>> env.reset(TensorDict({"params": torch.tensor([[1.0, 1.0], [3.0, 1.0]])}, [2]))
        Traceback (most recent call last):
        ...
        armeta_rl.errors.IdentifierError: tensordict key 'params' = [3.0, 1.0]: every ... [0.5, 1.5]
    """

    def __init__(self, space: TaskSpace) -> None:
        super().__init__(in_keys=[], out_keys=[])
        self.space = space

    def extend_task_space(self, base: TaskSpace | None) -> TaskSpace:
        return self.space

    def extend_identifier_check(self, base: IdentifierCheck | None) -> IdentifierCheck:
        space = self.space
        return IdentifierCheck(space.names, space.low, space.high, (False,) * space.dim)


def _boxed(make_env: Callable[[], EnvBase], space: TaskSpace, max_steps: int
          ) -> TaskTransformedEnv:
    """One instance of the user's env under its :class:`TaskBox`, its episodes cut to
    ``max_steps`` steps."""
    return TaskTransformedEnv(make_env(), Compose(TaskBox(space), StepCounter(max_steps)))


def _reshape(tensordict: Any, shape: tuple[int, ...]) -> Any:
    return tensordict.reshape(*shape)


def _instance_size(make_env: Callable[[], EnvBase]) -> int:
    """How many batch entries one instance of the user's env has (built once, under a forked
    RNG: building it draws nothing from the run's stream)."""
    with torch.random.fork_rng(devices=[]):
        env = make_env()
        try:
            return env.batch_size.numel()
        finally:
            env.close()


def one_task_envs(
    make_env: Callable[[], EnvBase],
    space: TaskSpace | Mapping[str, Any],
    batch_size: tuple[int, int],
    max_steps: int,
    parallel: bool = False,
    mp_start_method: str = "spawn",
) -> TaskTransformedEnv:
    """The ``[tasks, episodes]`` env of ``batch_size`` made of instances of ``make_env()``, one
    task each (module docstring), with episodes of at most ``max_steps`` steps.

    Args:
        make_env: builds one instance of the user's env (any batch size ``b``; ``prod(b)``
            episodes of its task).
        space: the task box ``{names, low, high}`` (the benchmark's ``space``).
        batch_size: ``(tasks, episodes)``.
        max_steps: the episode length limit (a ``StepCounter``).
        parallel: one process per instance (:class:`~armeta_rl.envs.TaskParallelEnv`); else
            all in this process (:class:`~armeta_rl.envs.TaskSerialEnv`).
        mp_start_method: how the processes start (``make_env`` must pickle for ``spawn``).

    Raises:
        ConfigError: ``episodes`` is not a multiple of an instance's batch size.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors.own_env import one_task_envs
        >>> from armeta_rl.envs import PendulumEnv
        >>> box = {"names": ["m", "l"], "low": [0.5, 0.5], "high": [1.5, 1.5]}
        >>> env = one_task_envs(lambda: PendulumEnv(batch_size=()), box, (2, 3), max_steps=10)
        >>> env.batch_size, env.task_space.names
        (torch.Size([2, 3]), ('m', 'l'))
        >>> tasks = torch.tensor([[0.5, 1.5], [1.5, 0.5]])[:, None].expand(2, 3, 2)
        >>> env.rollout(4, tensordict=env.reset(TensorDict({"params": tasks}, [2, 3])),
        ...             auto_reset=False)["params"][:, :, -1].equal(tasks)
        True
    """
    if isinstance(space, Mapping):
        space = TaskSpace(list(space["names"]), list(space["low"]), list(space["high"]))
    tasks, episodes = (int(n) for n in batch_size)
    per_instance = _instance_size(make_env)
    if episodes % per_instance:
        raise ConfigError(EPISODES_KEY, episodes,
                          f"must be a multiple of {per_instance}, the batch size of one instance "
                          "of the env (its entries are episodes of its one task)")
    worker = partial(_boxed, make_env, space, int(max_steps))
    count = tasks * episodes // per_instance
    batched = (TaskParallelEnv(count, worker, mp_start_method=mp_start_method) if parallel
               else TaskSerialEnv(count, worker))
    reshape = BatchSizeTransform(reshape_fn=partial(_reshape, shape=(tasks, episodes)))
    reshape.enable_inv_on_reset = True  # a reset's "params" [tasks, episodes, d] reach them
    return TaskTransformedEnv(batched, reshape)


class OneTaskEnvCollector(EpisodeCollector):
    """:class:`~armeta_rl.collectors.episodes.EpisodeCollector` over :func:`one_task_envs`: the
    collector a benchmark YAML names for a user's env (docs/own-env.md).

    Args:
        make_env: builds one instance of the user's env (a Hydra ``_partial_: true`` node).
        space: the benchmark's box (``${benchmark.space}``).
        episodes: episodes per task (a multiple of an instance's batch size).
        max_steps: the episode length limit.
        parallel: one process per instance.
        device: where the trajectories are returned.

    Raises:
        ConfigError: ``episodes`` is not a multiple of an instance's batch size.

    Examples:
        >>> import torch
        >>> from functools import partial
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors.own_env import OneTaskEnvCollector
        >>> from armeta_rl.envs.tutorial_pendulum import TutorialPendulumEnv
        >>> from armeta_rl.rl import GaussianMLP
        >>> box = {"names": ["m", "l"], "low": [0.5, 0.5], "high": [1.5, 1.5]}
        >>> make_env = partial(TutorialPendulumEnv, batch_size=(2,))  # 2 episodes an instance
        >>> collector = OneTaskEnvCollector(make_env, box, episodes=4, max_steps=5)
        >>> tasks = TensorDict({"params": torch.tensor([[0.5, 0.5], [1.5, 1.5]])}, [2])
        >>> _ = torch.manual_seed(0)
        >>> trajectories = collector.collect(tasks, policy=GaussianMLP(obs_dim=3, action_dim=1))
        >>> trajectories.batch_size  # [tasks, episodes, max_steps]: 2 instances per task
        torch.Size([2, 4, 5])
        >>> trajectories["params"][:, -1, -1]  # every episode of a task runs that task
        tensor([[0.5000, 0.5000],
                [1.5000, 1.5000]])
        >>> OneTaskEnvCollector(make_env, box, episodes=3)
        Traceback (most recent call last):
        ...
        armeta_rl.errors.ConfigError: config key 'benchmark.collector.episodes' = 3: must be ...
    """

    def __init__(self, make_env: Callable[[], EnvBase], space: Mapping[str, Any],
                 episodes: int = 20, max_steps: int = 100, parallel: bool = False,
                 device: torch.device = CPU) -> None:
        self.per_instance = _instance_size(make_env)
        if int(episodes) % self.per_instance:
            raise ConfigError(EPISODES_KEY, episodes, f"must be a multiple of "
                              f"{self.per_instance}, the batch size of one instance of the env")
        self.instance = partial(_boxed, make_env, TaskSpace(list(space["names"]),
                                                          list(space["low"]),
                                                          list(space["high"])), 1)
        build = partial(one_task_envs, make_env, dict(space), parallel=bool(parallel))
        super().__init__(build, episodes, max_steps, device)

    def probe_env(self) -> EnvBase:
        """One instance of the env under its box, to check boxes and read sizes on."""
        return self.instance()
