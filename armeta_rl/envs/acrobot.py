"""Batched acrobot with the two link masses as task identifiers (paper, appendix "System
Identification"; the "book" dynamics of gymnasium's ``Acrobot-v1``)."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Categorical

from armeta_rl.envs.identified_env import IdentifiedSystemEnv


def wrap_angle(angle: Tensor) -> Tensor:
    """Wrap into ``[-π, π)`` (gymnasium's ``wrap``; equal up to the value at ±π)."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


class AcrobotEnv(IdentifiedSystemEnv):
    """Gymnasium's ``Acrobot-v1`` (Sutton & Barto's "book" equations) for a batch
    ``[tasks, episodes]`` of two-link pendulums.

    State (θ1, θ2, θ̇1, θ̇2); one step integrates the equations of motion with one classical
    Runge–Kutta step of dt = 0.2 (gymnasium's ``rk4`` over ``[0, dt]``), wraps both angles to
    ``[-π, π)`` and clips the velocities to ±4π and ±9π. Initial states are uniform in
    ``[-0.1, 0.1]⁴``. An episode terminates when the tip rises above the bar,
    ``-cos θ1 - cos(θ1 + θ2) > 1`` (reward 0, else -1); inside ``env.rollout`` and TorchRL
    collectors the finished episodes are reset (partial reset) and collection goes on, keeping
    each task's masses. Wrap in ``torchrl.envs.StepCounter(max_steps=500)`` for gymnasium's
    time limit.

    Entries: ``"observation"`` (cos θ1, sin θ1, cos θ2, sin θ2, θ̇1, θ̇2), ``"state"``,
    ``"params"`` (m1, m2) = gymnasium's ``LINK_MASS_1``, ``LINK_MASS_2``, and ``"action"``
    ``[*batch]``: a categorical index in {0, 1, 2} applying torque ``action - 1`` ∈ {-1, 0, +1}
    (gymnasium's ``AVAIL_TORQUE[action]``).
    """

    param_names = ("m1", "m2")
    default_params = (1.0, 1.0)
    state_dim = 4
    observation_dim = 6
    dt = 0.2
    g = 9.8
    link_length_1 = 1.0
    link_com_1 = 0.5
    link_com_2 = 0.5
    link_moi = 1.0
    max_vel_1 = 4 * math.pi
    max_vel_2 = 9 * math.pi
    max_torque = 1.0
    observation_high = (1.0, 1.0, 1.0, 1.0, max_vel_1, max_vel_2)

    @staticmethod
    def torque(action: Tensor) -> Tensor:
        """Torque ``action - 1`` ∈ {-1, 0, +1} as a float ``[..., 1]``."""
        return (action.to(torch.get_default_dtype()) - 1.0).unsqueeze(-1)

    def _make_action_spec(self) -> Categorical:
        return Categorical(n=3, shape=self.batch_size, dtype=torch.int64, device=self.device)

    def _initial_state(self) -> Tensor:
        return self._uniform(-0.1, 0.1)

    def _observe(self, state: Tensor) -> Tensor:
        theta1, theta2, dtheta1, dtheta2 = state.unbind(-1)
        return torch.stack(
            [theta1.cos(), theta1.sin(), theta2.cos(), theta2.sin(), dtheta1, dtheta2], -1)

    def _coefficients(self, params: Tensor) -> tuple[Tensor, ...]:
        """Mass-dependent constants of the equations of motion, once per step."""
        m1, m2 = params.unbind(-1)
        l1, lc1, lc2, inertia = self.link_length_1, self.link_com_1, self.link_com_2, self.link_moi
        return (
            m1 * lc1**2 + m2 * (l1**2 + lc2**2) + 2 * inertia,  # d1 without its cos θ2 term
            m2 * l1 * lc2,
            m2 * lc2**2 + inertia,
            m2 * lc2 * self.g,
            (m1 * lc1 + m2 * l1) * self.g,
        )

    @staticmethod
    def _derivatives(state: Tensor, torque: Tensor, coefficients: tuple[Tensor, ...]) -> Tensor:
        """ds/dt of the book equations (gymnasium's ``AcrobotEnv._dsdt``), with
        cos(θ1 + θ2 − π/2) = sin(θ1 + θ2) and cos(θ1 − π/2) = sin θ1."""
        d1_rest, coupling, d2_rest, gravity2, gravity1 = coefficients
        theta1, theta2, dtheta1, dtheta2 = state.unbind(-1)
        cos2, sin2 = theta2.cos(), theta2.sin()
        d1 = d1_rest + 2 * coupling * cos2
        d2 = d2_rest + coupling * cos2
        phi2 = gravity2 * torch.sin(theta1 + theta2)
        phi1 = -coupling * sin2 * dtheta2 * (dtheta2 + 2 * dtheta1) + gravity1 * theta1.sin() + phi2
        ddtheta2 = (torque + d2 / d1 * phi1 - coupling * dtheta1**2 * sin2 - phi2) / (
            d2_rest - d2**2 / d1
        )
        ddtheta1 = -(d2 * ddtheta2 + phi1) / d1
        return torch.stack([dtheta1, dtheta2, ddtheta1, ddtheta2], -1)

    def _rk4(self, state: Tensor, torque: Tensor, params: Tensor) -> Tensor:
        """One classical Runge–Kutta step of length dt (gymnasium's ``rk4``)."""
        coefficients, half = self._coefficients(params), self.dt / 2.0
        k1 = self._derivatives(state, torque, coefficients)
        k2 = self._derivatives(state + half * k1, torque, coefficients)
        k3 = self._derivatives(state + half * k2, torque, coefficients)
        k4 = self._derivatives(state + self.dt * k3, torque, coefficients)
        return state + self.dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        params = tensordict["params"]
        torque = self.torque(tensordict["action"]).squeeze(-1).to(self.dtype)
        theta1, theta2, dtheta1, dtheta2 = self._rk4(tensordict["state"], torque, params).unbind(-1)
        state = torch.stack(
            [
                wrap_angle(theta1),
                wrap_angle(theta2),
                dtheta1.clamp(-self.max_vel_1, self.max_vel_1),
                dtheta2.clamp(-self.max_vel_2, self.max_vel_2),
            ],
            -1,
        )
        terminated = (-state[..., 0].cos() - (state[..., 1] + state[..., 0]).cos() > 1.0)
        terminated = terminated.unsqueeze(-1)
        return TensorDict(
            {
                "state": state,
                "observation": self._observe(state),
                "params": params,
                "reward": terminated.to(self.dtype) - 1.0,
                "done": terminated,
                "terminated": terminated.clone(),
            },
            batch_size=self.batch_size,
            device=self.device,
        )
