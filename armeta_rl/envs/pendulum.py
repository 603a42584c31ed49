"""Batched pendulum with mass and length as task identifiers (paper, appendix "System
Identification"; the dynamics of gymnasium's ``Pendulum-v1``)."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded

from armeta_rl.envs.identified_env import IdentifiedSystemEnv


def angle_normalize(angle: Tensor) -> Tensor:
    """Wrap an angle into ``[-π, π)`` (gymnasium's ``angle_normalize``)."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


class PendulumEnv(IdentifiedSystemEnv):
    """Gymnasium's ``Pendulum-v1`` for a batch ``[tasks, episodes]`` of pendulums.

    Each step (dt = 0.05, g = 10), with torque ``u`` clipped to ``[-2, 2]``::

        θ̇' = clip(θ̇ + (3g / (2l) sin θ + 3 / (m l²) u) dt, -8, 8),   θ' = θ + θ̇' dt

    and reward ``-(normalize(θ)² + 0.1 θ̇² + 0.001 u²)``. The angle is kept wrapped to
    ``[-π, π)`` (the dynamics only see it through ``sin``). Initial states are uniform,
    θ ∈ [-π, π], θ̇ ∈ [-1, 1]. The pendulum never terminates; wrap the env in
    ``torchrl.envs.StepCounter(max_steps=200)`` for gymnasium's time limit.

    Entries: ``"observation"`` (cos θ, sin θ, θ̇), ``"state"`` (θ, θ̇), ``"params"`` (m, l),
    ``"action"`` ``[*batch, 1]`` (the torque).
    """

    param_names = ("m", "l")
    default_params = (1.0, 1.0)
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

    def _make_action_spec(self) -> Bounded:
        return Bounded(low=-self.max_torque, high=self.max_torque, shape=(*self.batch_size, 1),
                       dtype=self.dtype, device=self.device)

    def _initial_state(self) -> Tensor:
        unit = self._uniform(-1.0, 1.0)
        return unit * torch.tensor([math.pi, 1.0], dtype=self.dtype, device=self.device)

    def _observe(self, state: Tensor) -> Tensor:
        theta, theta_dot = state.unbind(-1)
        return torch.stack([theta.cos(), theta.sin(), theta_dot], -1)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        theta, theta_dot = tensordict["state"].unbind(-1)
        params = tensordict["params"]
        mass, length = params.unbind(-1)
        torque = self.torque(tensordict["action"]).squeeze(-1).to(self.dtype)
        cost = angle_normalize(theta) ** 2 + 0.1 * theta_dot**2 + 0.001 * torque**2
        acceleration = 3 * self.g / (2 * length) * theta.sin() + 3.0 / (mass * length**2) * torque
        theta_dot = (theta_dot + acceleration * self.dt).clamp(-self.max_speed, self.max_speed)
        state = torch.stack([angle_normalize(theta + theta_dot * self.dt), theta_dot], -1)
        done = torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device)
        return TensorDict(
            {
                "state": state,
                "observation": self._observe(state),
                "params": params,
                "reward": -cost.unsqueeze(-1),
                "done": done,
                "terminated": done.clone(),
            },
            batch_size=self.batch_size,
            device=self.device,
        )
