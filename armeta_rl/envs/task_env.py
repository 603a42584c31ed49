"""Task envs in TorchRL's layouts: the task box and reset contract of an env behind transforms or
in batched envs, and TorchRL's wrappers as drop-ins that carry them.

:func:`task_space` and :func:`identifier_check` read an env's box and reset contract
(:class:`~armeta_rl.tasks.protocol.IdentifierCheck`) through any ``TransformedEnv`` (a
transform that adds identifiers, :class:`~armeta_rl.envs.mujoco_tasks.PhysicsTaskTransform`,
extends them) and batched env. TorchRL's own wrappers forward attribute reads to the env inside,
which tells only its own box (a ``SerialEnv`` fails on them before it starts and answers a list
after), so the package gives drop-ins:

* :class:`TaskTransformedEnv` is TorchRL's ``TransformedEnv`` with ``task_space``, ``p0`` and
  ``identifier_check`` of the whole env, and a reset that refuses a misplaced identifier key
  (``"param"``) and takes nested identifiers before TorchRL's selection of state keys drops or
  passes them, a partial (``"_reset"``) reset too. The package's wrappers
  (:func:`~armeta_rl.envs.mujoco_tasks.physics_task_env`,
  :func:`~armeta_rl.envs.mujoco_tasks.make_gym_task_env`) return one.
* :class:`TaskSerialEnv` and :class:`TaskParallelEnv` are TorchRL's ``SerialEnv`` and
  ``ParallelEnv`` with one ``task_space`` and ``p0`` (refused in one line where the workers'
  boxes differ), read from the env each worker is built as when TorchRL builds one to read its
  specs. Every reset is checked with the workers' contract in the calling process before any
  worker sees it: a refused reset is the one-line
  :class:`~armeta_rl.errors.IdentifierError` with the workers alive (TorchRL's ``ParallelEnv``
  loses a worker whose env raises), and a full reset that a ``TransformedEnv`` in front left
  without identifiers (a misspelled key) is refused rather than handed to the workers as a plain
  ``reset()``.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from tensordict import TensorDictBase
from torchrl.envs import Compose, EnvBase, ParallelEnv, SerialEnv, Transform, TransformedEnv
from torchrl.envs.batched_envs import BatchedEnvBase

from armeta_rl.errors import ConfigError
from armeta_rl.tasks.distributions import BoxUniform, TaskEnvMixin
from armeta_rl.tasks.protocol import TASK_KEY, IdentifierCheck
from armeta_rl.tasks.space import TaskSpace


def _transforms(transform: Transform) -> Iterator[Transform]:
    """The transforms of ``transform`` in order, Composes flattened."""
    if isinstance(transform, Compose):
        for inner in transform.transforms:
            yield from _transforms(inner)
    else:
        yield transform


def _describe(env: EnvBase, name: str) -> Any:
    """The ``task_space`` or ``identifier_check`` (``name``) of ``env`` through its wrappers, or
    ``None`` where it tells none; a transform with ``extend_<name>`` changes its base env's."""
    if isinstance(env, TransformedEnv):
        value = _describe(env.base_env, name)
        for transform in _transforms(env.transform):
            extend = getattr(transform, f"extend_{name}", None)
            if extend is not None:
                value = extend(value)
        return value
    if isinstance(env, TaskBatchedEnv):
        return env.worker_value(name)
    if isinstance(env, SerialEnv) and not env.is_closed:
        values = [_describe(sub, name) for sub in env._envs]
        return values[0] if all(v == values[0] for v in values) else None
    if isinstance(env, TaskEnvMixin):
        return getattr(env, name)
    return None


def task_space(env: EnvBase) -> TaskSpace:
    """The box of ``env``'s identifiers, in the order of ``"params"``, through any transforms
    and batched envs: the base env's own identifiers, then those a transform adds (a
    :class:`~armeta_rl.envs.mujoco_tasks.PhysicsTaskTransform`'s physics).

    Raises:
        ConfigError: ``env`` tells no box: it takes no identifiers, or it is a TorchRL
            ``ParallelEnv`` (or an unstarted ``SerialEnv``), whose workers the calling process
            cannot ask (:class:`TaskParallelEnv` can).

    Examples:
        >>> from torchrl.envs import StepCounter, TransformedEnv
        >>> from armeta_rl.envs import HalfCheetahVelEnv, task_space
        >>> from armeta_rl.envs.mujoco_tasks import physics_task_env
        >>> mass = {"name": "mass_scale", "kind": "body_mass_only_scale", "target": "all",
        ...         "low": 0.75, "high": 1.25}
        >>> env = physics_task_env(HalfCheetahVelEnv, [mass], batch_size=(2, 1))
        >>> task_space(TransformedEnv(env, StepCounter(200))).names
        ('goal_velocity', 'mass_scale')
    """
    space = _describe(env, "task_space")
    if space is None:
        raise ConfigError("env", type(env).__name__,
                          "tells no task box: it takes no identifiers under 'params', or it is "
                          "a TorchRL ParallelEnv or unstarted SerialEnv (build it as "
                          "armeta_rl.envs.TaskParallelEnv or TaskSerialEnv)")
    return space


def identifier_check(env: EnvBase) -> IdentifierCheck | None:
    """The reset contract of ``env`` through any transforms and batched envs (``None``: its
    resets take no identifiers, e.g. a ``TaskTransform`` with a source provides them).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.envs import StepCounter, TransformedEnv
        >>> from armeta_rl.envs import PendulumEnv, identifier_check
        >>> check = identifier_check(TransformedEnv(PendulumEnv(batch_size=(3,)), StepCounter(9)))
        >>> check.names, check.low, check.high, check.open_low  # m and l in (0, inf)
        (('m', 'l'), (0.0, 0.0), (inf, inf), (True, True))
        >>> check.read(TensorDict({"params": torch.tensor([2.0, 0.5])}, []), torch.Size([3]))
        tensor([[2.0000, 0.5000],
                [2.0000, 0.5000],
                [2.0000, 0.5000]])
        >>> check.read(TensorDict({"params": torch.tensor([0.0, 0.5])}, []), torch.Size([3]))
        Traceback (most recent call last):
        ...
        armeta_rl.errors.IdentifierError: tensordict key 'params' = [0.0, 0.5]: every ... (0, inf)
    """
    return _describe(env, "identifier_check")


class _TellsItsBox:
    """An env that tells the box of all its identifiers (:func:`task_space`: through its
    transforms, one for all the workers of a batched env) and p0, uniform on it."""

    @property
    def task_space(self) -> TaskSpace:
        """The box of the env's identifiers (:func:`task_space`)."""
        return task_space(self)

    @property
    def p0(self) -> BoxUniform:
        """Uniform on :attr:`task_space`."""
        return BoxUniform(self.task_space)


class TaskTransformedEnv(_TellsItsBox, TransformedEnv):
    """TorchRL's ``TransformedEnv`` that tells the task box of the whole env and refuses a
    misplaced identifier key before TorchRL's selection of reset keys drops it (module
    docstring); otherwise the same env, step for step.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.envs import StepCounter
        >>> from armeta_rl.envs import PendulumEnv, TaskTransformedEnv
        >>> env = TaskTransformedEnv(PendulumEnv(batch_size=(2,)), StepCounter(200))
        >>> env.task_space.names, type(env.p0).__name__
        (('m', 'l'), 'BoxUniform')
        >>> env.reset(TensorDict({"param": torch.ones(2, 2), "_reset": torch.ones(2, 1,
        ...                       dtype=torch.bool)}, [2]))
        Traceback (most recent call last):
        ...
        armeta_rl.errors.IdentifierError: tensordict key 'param' = tensor of shape [2, 2], ...
    """

    @property
    def identifier_check(self) -> IdentifierCheck | None:
        """The whole env's reset contract (:func:`identifier_check`)."""
        return identifier_check(self)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        check = self.identifier_check if tensordict is not None else None
        if check is not None:
            check.refuse_misplaced(tensordict)
            params = tensordict.get(TASK_KEY, None)
            if isinstance(params, TensorDictBase):
                tensordict = tensordict.exclude(TASK_KEY).set(TASK_KEY, check.flat(params))
        return super()._reset(tensordict, **kwargs)


class TaskBatchedEnv(_TellsItsBox):
    """What :class:`TaskSerialEnv` and :class:`TaskParallelEnv` add to TorchRL's batched envs
    (module docstring): the workers' box and contract, read from the env TorchRL builds of each
    to read its specs, and every reset checked in the calling process.

    Examples:
        >>> from armeta_rl.collectors.own_env import TaskBox
        >>> from armeta_rl.envs import TaskSerialEnv, TaskTransformedEnv
        >>> from armeta_rl.envs.task_env import TaskBatchedEnv
        >>> from armeta_rl.envs.tutorial_pendulum import TutorialPendulumEnv
        >>> from armeta_rl.tasks import TaskSpace
        >>> def pendulum(high):  # a user's env, its box declared by a TaskBox
        ...     box = TaskSpace(["m", "l"], low=[0.5, 0.5], high=[high, high])
        ...     return TaskTransformedEnv(TutorialPendulumEnv(), TaskBox(box))
        >>> env = TaskSerialEnv(2, lambda: pendulum(1.5))
        >>> isinstance(env, TaskBatchedEnv), env.task_space.high, env.identifier_check.low
        (True, (1.5, 1.5), (0.5, 0.5))
        >>> TaskSerialEnv(2, [lambda: pendulum(1.5), lambda: pendulum(2.0)]).task_space
        Traceback (most recent call last):
        ...
        armeta_rl.errors.ConfigError: config key 'env' = 'TaskSerialEnv': its workers differ ...
    """

    def _get_metadata(self, create_env_fn: list, create_env_kwargs: list) -> None:
        self.__dict__["_task_workers"] = []
        super()._get_metadata(create_env_fn, create_env_kwargs)

    def _validate_worker_env(self, env: EnvBase) -> None:
        BatchedEnvBase._validate_worker_env(env)
        self._task_workers.append({name: _describe(env, name)
                                   for name in ("task_space", "identifier_check")})

    def worker_value(self, name: str) -> Any:
        """The workers' ``task_space`` or ``identifier_check``, where they agree; a
        :class:`ConfigError` where they differ."""
        values = [worker[name] for worker in self._task_workers]
        if any(value != values[0] for value in values):
            raise ConfigError("env", type(self).__name__,
                              f"its workers differ in their {name.replace('_', ' ')} "
                              f"({', '.join(dict.fromkeys(map(str, values)))}): one "
                              "batched env holds tasks of one box")
        return values[0]

    @property
    def identifier_check(self) -> IdentifierCheck | None:
        """The workers' reset contract (one for all of them)."""
        return self.worker_value("identifier_check")

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        """Check the reset with the workers' contract here, then hand it to them."""
        checks = [worker["identifier_check"] for worker in self._task_workers]
        if all(check == checks[0] for check in checks):
            if checks[0] is not None:
                tensordict = _checked(checks[0], tensordict, self.batch_size)
        else:
            for i, check in enumerate(checks):
                if check is not None:
                    check.read(None if tensordict is None else tensordict[i], self.batch_size[1:])
        return super()._reset(tensordict, **kwargs)


def _checked(check: IdentifierCheck, tensordict: TensorDictBase | None, batch_size: Any
             ) -> TensorDictBase | None:
    """``tensordict`` once ``check`` accepts it, nested identifiers stacked in the check's
    order."""
    check.read(tensordict, batch_size)
    params = None if tensordict is None else tensordict.get(TASK_KEY, None)
    if isinstance(params, TensorDictBase):
        return tensordict.exclude(TASK_KEY).set(TASK_KEY, check.flat(params))
    return tensordict


class TaskSerialEnv(TaskBatchedEnv, SerialEnv):
    """TorchRL's ``SerialEnv`` with one task box and every reset checked before the workers see
    it (module docstring); the same env otherwise.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.envs import StepCounter, TransformedEnv
        >>> from armeta_rl.envs import PendulumEnv, TaskSerialEnv
        >>> env = TransformedEnv(TaskSerialEnv(2, lambda: PendulumEnv(batch_size=(3,))),
        ...                      StepCounter(200))
        >>> env.task_space.names
        ('m', 'l')
        >>> env.reset(TensorDict({"param": torch.ones(2, 3, 2)}, [2, 3]))
        Traceback (most recent call last):
        ...
        armeta_rl.errors.IdentifierError: tensordict key 'params' = missing: a full reset's ...
    """


class TaskParallelEnv(TaskBatchedEnv, ParallelEnv):
    """TorchRL's ``ParallelEnv`` with one task box and every reset checked in the calling process
    before a worker sees it, so a refused reset leaves the workers alive (module docstring); the
    same env otherwise.

    Examples:
        >>> import torch
        >>> from functools import partial
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import PendulumEnv, TaskParallelEnv
        >>> env = TaskParallelEnv(2, partial(PendulumEnv, batch_size=(3,)))  # 2 processes
        >>> env.task_space.names, type(env.p0).__name__  # read without starting a process
        (('m', 'l'), 'BoxUniform')
        >>> tasks = torch.tensor([[1.0, 1.0], [-1.0, 1.0]])[:, None].expand(2, 3, 2)
        >>> env.reset(TensorDict({"params": tasks}, [2, 3]))
        Traceback (most recent call last):
        ...
        armeta_rl.errors.IdentifierError: tensordict key 'params' = [-1.0, 1.0]: every ... (0, inf)
        >>> env.is_closed  # refused in this process, before any worker started
        True
    """
