"""TorchRL's pendulum tutorial env (pytorch.org/rl, "Pendulum: Writing your environment and
transforms with TorchRL"), written as a user writes their own env, with its physical parameters
(m, l) as the task: the example docs/own-env.md meta-trains through
:class:`~armeta_rl.collectors.own_env.OneTaskEnvCollector` and ``benchmark=tutorial_pendulum``.
It uses nothing of the package but :data:`~armeta_rl.tasks.TASK_KEY`."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from armeta_rl.tasks import TASK_KEY


class TutorialPendulumEnv(EnvBase):
    """The tutorial's pendulum (gymnasium's Pendulum-v1 dynamics) with one task, its mass and
    length ``(m, l)``, under ``"params"``: set by a reset that carries it, kept by every other
    reset. Any batch size; every entry runs the instance's one task.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs.tutorial_pendulum import TutorialPendulumEnv
        >>> env = TutorialPendulumEnv(batch_size=(4,), seed=0)
        >>> start = env.reset(TensorDict({"params": torch.tensor([0.5, 1.5]).expand(4, 2)}, [4]))
        >>> env.rollout(3, tensordict=start, auto_reset=False)["params"][0, -1]
        tensor([0.5000, 1.5000])
    """

    max_speed, max_torque, dt, g = 8.0, 2.0, 0.05, 10.0

    def __init__(self, batch_size: Sequence[int] = (), seed: int = 0) -> None:
        super().__init__(batch_size=torch.Size(batch_size))
        shape = self.batch_size
        self.task = torch.ones(*shape, 2)  # (m, l)
        angle = Unbounded(shape=shape)
        self.observation_spec = Composite(observation=Unbounded(shape=(*shape, 3)), th=angle,
                                          thdot=angle.clone(),
                                          params=Unbounded(shape=(*shape, 2)), shape=shape)
        # the state a step reads, and the task: TorchRL's wrappers forward state keys at reset
        self.state_spec = Composite(th=angle.clone(), thdot=angle.clone(),
                                    params=Unbounded(shape=(*shape, 2)), shape=shape)
        self.action_spec = Bounded(-self.max_torque, self.max_torque, shape=(*shape, 1))
        self.reward_spec = Unbounded(shape=(*shape, 1))
        done = Categorical(2, shape=(*shape, 1), dtype=torch.bool)
        self.done_spec = Composite(done=done, terminated=done.clone(), shape=shape)
        self.rng = torch.Generator()
        self.set_seed(seed)

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(0 if seed is None else int(seed))

    def _observe(self, th: torch.Tensor, thdot: torch.Tensor, **entries: torch.Tensor
                 ) -> TensorDict:
        observation = torch.stack([th.cos(), th.sin(), thdot], -1)
        return TensorDict({"th": th, "thdot": thdot, "observation": observation,
                           TASK_KEY: self.task.clone(), **entries}, self.batch_size)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        task = None if tensordict is None else tensordict.get(TASK_KEY, None)
        if task is not None:
            reset = tensordict.get("_reset", torch.ones(*self.batch_size, 1, dtype=torch.bool))
            self.task = torch.where(reset, task.expand(*self.batch_size, 2), self.task)
        th = (torch.rand(self.batch_size, generator=self.rng) * 2 - 1) * math.pi
        thdot = torch.rand(self.batch_size, generator=self.rng) * 2 - 1
        return self._observe(th, thdot)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        th, thdot = tensordict["th"], tensordict["thdot"]
        torque = tensordict["action"].squeeze(-1).clamp(-self.max_torque, self.max_torque)
        mass, length = self.task.unbind(-1)
        upright = (th + math.pi) % (2 * math.pi) - math.pi
        cost = upright**2 + 0.1 * thdot**2 + 0.001 * torque**2
        thdot = thdot + (3 * self.g / (2 * length) * th.sin()
                         + 3.0 / (mass * length**2) * torque) * self.dt
        thdot = thdot.clamp(-self.max_speed, self.max_speed)
        done = torch.zeros(*self.batch_size, 1, dtype=torch.bool)
        return self._observe(th + thdot * self.dt, thdot, reward=-cost.unsqueeze(-1), done=done,
                             terminated=done.clone())
