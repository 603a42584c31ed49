"""Batched pendulum with mass and length (and optionally gravity) as task identifiers (paper,
appendix "System Identification"; the dynamics of gymnasium's ``Pendulum-v1``)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from armeta_rl.envs.identified_env import IdentifiedSystemEnv, UniformBounded


class PendulumEnv(IdentifiedSystemEnv):
    """Gymnasium's ``Pendulum-v1`` for a batch ``[tasks, episodes]`` of pendulums.

    Each step (dt = 0.05, g = 10 unless an identifier), with torque ``u`` clipped to
    ``[-2, 2]``::

        θ̇' = clip(θ̇ + (3g / (2l) sin θ + 3 / (m l²) u) dt, -8, 8),   θ' = θ + θ̇' dt

    and reward ``-(normalize(θ)² + 0.1 θ̇² + 0.001 u²)``. The angle is kept wrapped to
    ``[-π, π)`` (the dynamics only see it through ``sin``). Initial states are uniform,
    θ ∈ [-π, π], θ̇ ∈ [-1, 1]. The pendulum never terminates; wrap the env in
    ``torchrl.envs.StepCounter(max_steps=200)`` for gymnasium's time limit.

    Entries: ``"observation"`` (cos θ, sin θ, θ̇), ``"state"`` (θ, θ̇), ``"params"`` (m, l by
    default; ``identifiers=("m", "l", "g")`` adds gravity, any subset of the three may be
    chosen), ``"action"`` ``[*batch, 1]`` (the torque).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import PendulumEnv
        >>> from armeta_rl.tasks import TASK_KEY
        >>> env = PendulumEnv(batch_size=(2, 1), seed=0)  # 2 tasks x 1 episode
        >>> task = torch.tensor([[1.0, 0.5], [1.0, 1.5]])[:, None]  # (m, l): short, long
        >>> start = env.reset(TensorDict({TASK_KEY: task}, [2, 1]))
        >>> idle = lambda td: td.set("action", torch.zeros(2, 1, 1))  # no torque
        >>> step = env.rollout(1, idle, tensordict=start, auto_reset=False)
        >>> _, sin, speed = start["observation"].unbind(-1)  # (cos θ, sin θ, θ̇)
        >>> ((step["next", "observation"][..., 0, 2] - speed) / sin).flatten()  # 3g/(2l)·dt
        tensor([1.5000, 0.5000])
    """

    param_names = ("m", "l")
    identifier_defaults = {"m": 1.0, "l": 1.0, "g": 10.0}
    task_boxes = {"m": (0.4, 1.6), "l": (0.4, 1.6), "g": (5.0, 15.0)}
    state_dim = 2
    observation_dim = 3
    dt = 0.05
    g = 10.0
    max_speed = 8.0
    max_torque = 2.0
    observation_high = (1.0, 1.0, max_speed)

    @staticmethod
    def torque(action: Tensor) -> Tensor:
        """The action is the torque, clipped to ``[-2, 2]``."""
        return action.clamp(-PendulumEnv.max_torque, PendulumEnv.max_torque)

    def _make_action_spec(self) -> UniformBounded:
        return UniformBounded(low=-self.max_torque, high=self.max_torque,
                              shape=(*self.batch_size, 1), dtype=self.dtype, device=self.device)

    def _precompute(self) -> None:
        self.initial_scale = torch.tensor([math.pi, 1.0], dtype=self.dtype, device=self.device)
        # dt as a 0-dim tensor, as the base class keeps π: cheaper ops than with a Python number
        self.step_time = torch.tensor(self.dt, dtype=self.dtype, device=self.device)

    def _physical_constants(self, params: Tensor) -> Tensor:
        """Per env ``(3g / (2l) dt, 3 / (m l²) dt)``: the velocity change per unit of sin θ
        and of torque; m, l and g are the identifiers or their defaults."""
        named = dict(zip(self.param_names, params.unbind(-1), strict=True))
        ones = params.new_ones(params.shape[0])
        mass, length, g = (named.get(name, ones * self.identifier_defaults[name])
                           for name in ("m", "l", "g"))
        # reciprocal then product, the rounding of ``3 * 10.0 / tensor`` (Tensor.__rtruediv__),
        # which the seeded pendulum results are computed with
        gravity = (2 * length).reciprocal() * (3 * g) * self.dt
        inertia = 3.0 / (mass * length**2) * self.dt
        return torch.stack([gravity, inertia], -1)

    def _initial_state(self) -> Tensor:
        return self._uniform(-1.0, 1.0) * self.initial_scale

    def _observe_rows(self, state: Tensor) -> Tensor:
        """From feature-major states ``[2, n_envs]``: (cos θ, sin θ, θ̇) ``[3, n_envs]``."""
        theta, theta_dot = state
        return torch.stack([theta.cos(), theta.sin(), theta_dot])

    def _random_actions(self, steps: int) -> Tensor:
        action = torch.empty((steps, *self.batch_size, 1), dtype=self.dtype, device=self.device)
        return action.uniform_(-self.max_torque, self.max_torque)

    def _torques(self, action: Tensor) -> Tensor:
        """The clipped torques ``[n]`` of actions ``[n, 1]`` (or the batch's ``[*batch, 1]``)."""
        return self.torque(action.reshape(-1)).to(self.dtype)

    def _forcing(self, action: Tensor) -> Tensor:
        """The velocity change 3 / (m l²) · u · dt of each clipped torque u."""
        inertia = self.constants[1]  # 3 / (m l²) dt
        return inertia * self.torque(self._per_env(action)).to(self.dtype)

    def _dynamics(self, state: Tensor, forcing: Tensor) -> Tensor:
        theta, theta_dot = state.unbind()
        gravity = self.constants[0]  # 3g / (2l) dt
        new_theta_dot = theta_dot + gravity * theta.sin() + forcing
        new_theta_dot = new_theta_dot.clamp(-self.max_speed, self.max_speed)
        new_theta = self._wrap_angles_(theta + new_theta_dot * self.step_time)
        return torch.stack([new_theta, new_theta_dot])

    def _reward(self, state: Tensor, action: Tensor, new_state: Tensor) -> Tensor:
        """-(normalize(θ)² + 0.1 θ̇² + 0.001 u²) at the step's start."""
        theta, theta_dot = state
        torque = self._torques(action)
        normalized = self._wrap_angles_(theta.clone())
        return -(normalized.square() + 0.1 * theta_dot.square() + 0.001 * torque.square())
