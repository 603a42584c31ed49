"""Batched acrobot with the two link masses as task identifiers (paper, appendix "System
Identification"; the "book" dynamics of gymnasium's ``Acrobot-v1``)."""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torchrl.data import Categorical

from armeta_rl.envs.identified_env import IdentifiedSystemEnv


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

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import AcrobotEnv
        >>> from armeta_rl.tasks import TASK_KEY
        >>> env = AcrobotEnv(batch_size=(2, 1), seed=0)  # 2 tasks x 1 episode
        >>> task = torch.tensor([[1.0, 1.0], [1.0, 3.0]])[:, None]  # masses (m1, m2)
        >>> start = env.reset(TensorDict({TASK_KEY: task}, [2, 1]))
        >>> push = lambda td: td.set("action", torch.full((2, 1), 2))  # torque +1
        >>> steps = env.rollout(3, push, tensordict=start, auto_reset=False)
        >>> cos1, sin1, cos2, sin2 = steps["next", "observation"][..., :4].unbind(-1)
        >>> (-cos1 - (cos1 * cos2 - sin1 * sin2)).round(decimals=2)  # the tip, 1 is the bar
        tensor([[[-2.0000, -2.0000, -1.9900]],
        <BLANKLINE>
                [[-2.0000, -2.0000, -1.9900]]])
        >>> steps["next", "reward"].squeeze(-1)  # -1 a step until the tip is above the bar
        tensor([[[-1., -1., -1.]],
        <BLANKLINE>
                [[-1., -1., -1.]]])
    """

    param_names = ("m1", "m2")
    identifier_defaults = {"m1": 1.0, "m2": 1.0}
    task_boxes = {"m1": (0.4, 1.6), "m2": (0.4, 1.6)}
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

    def _precompute(self) -> None:
        # gymnasium's AVAIL_TORQUE: the torque of each action
        self.available_torque = torch.tensor([-1.0, 0.0, 1.0], dtype=self.dtype,
                                             device=self.device)
        # The physics works on feature-major states [4, n_envs] (contiguous rows).
        self.max_velocity = torch.tensor([[self.max_vel_1], [self.max_vel_2]], dtype=self.dtype,
                                         device=self.device)
        self.min_velocity = -self.max_velocity

    def _physical_constants(self, params: Tensor) -> Tensor:
        """Per env the mass-dependent constants of the equations of motion, all affine in
        (m1, m2): d1 without its cos θ2 term, 2 × coupling, coupling ``m2 l1 lc2``,
        ``d2_rest = m2 lc2² + I``, and the gravity factors of φ2 and φ1."""
        l1, lc1, lc2, inertia = self.link_length_1, self.link_com_1, self.link_com_2, self.link_moi
        weights = torch.tensor(
            [
                [lc1**2, 0.0, 0.0, 0.0, 0.0, lc1 * self.g],
                [l1**2 + lc2**2, 2 * l1 * lc2, l1 * lc2, lc2**2, lc2 * self.g, l1 * self.g],
            ],
            dtype=params.dtype,
            device=params.device,
        )
        bias = torch.tensor([2 * inertia, 0.0, 0.0, inertia, 0.0, 0.0], dtype=params.dtype,
                            device=params.device)
        return torch.addmm(bias, params, weights)

    def _initial_state(self) -> Tensor:
        return self._uniform(-0.1, 0.1)

    def _observe_rows(self, state: Tensor) -> Tensor:
        """From feature-major states ``[4, n_envs]``: (cos θ1, sin θ1, cos θ2, sin θ2, θ̇1, θ̇2)
        ``[6, n_envs]``."""
        theta1, theta2, dtheta1, dtheta2 = state.unbind()
        return torch.stack([theta1.cos(), theta1.sin(), theta2.cos(), theta2.sin(), dtheta1,
                            dtheta2])

    def _derivatives(self, state: Tensor, torque: Tensor) -> Tensor:
        """ds/dt ``[4, n_envs]`` of the book equations (gymnasium's ``AcrobotEnv._dsdt``) at
        feature-major states ``[4, n_envs]``; gymnasium's cos(θ1 + θ2 − π/2) and cos(θ1 − π/2)
        are written sin(θ1 + θ2) and sin θ1."""
        theta1, theta2, dtheta1, dtheta2 = state.unbind()
        d1_rest, two_coupling, coupling, d2_rest, gravity2, gravity1 = self.constants
        sin2, cos2 = theta2.sin(), theta2.cos()
        d1 = d1_rest + two_coupling * cos2
        d2 = d2_rest + coupling * cos2
        phi2 = gravity2 * (theta1 + theta2).sin()
        coupled = coupling * sin2  # m2 l1 lc2 sin θ2
        # gymnasium's m2 l1 lc2 θ̇2² sin θ2 + 2 m2 l1 lc2 θ̇2 θ̇1 sin θ2, factored
        velocity_terms = coupled * dtheta2 * torch.add(dtheta2, dtheta1, alpha=2)
        phi1 = gravity1 * theta1.sin() - velocity_terms + phi2
        ddtheta2 = ((torque + d2 / d1 * phi1 - coupled * dtheta1.square() - phi2)
                    / (d2_rest - d2.square() / d1))
        ddtheta1 = -(d2 * ddtheta2 + phi1) / d1
        return torch.stack([dtheta1, dtheta2, ddtheta1, ddtheta2])

    def _rk4(self, state: Tensor, torque: Tensor) -> Tensor:
        """One classical Runge–Kutta step of length dt (gymnasium's ``rk4``)."""
        half = self.dt / 2.0
        k1 = self._derivatives(state, torque)
        k2 = self._derivatives(torch.add(state, k1, alpha=half), torque)
        k3 = self._derivatives(torch.add(state, k2, alpha=half), torque)
        k4 = self._derivatives(torch.add(state, k3, alpha=self.dt), torque)
        slope = torch.add(k1, k4).add_(k2, alpha=2.0).add_(k3, alpha=2.0)
        return torch.add(state, slope, alpha=self.dt / 6.0)

    def _random_actions(self, steps: int) -> Tensor:
        return torch.randint(0, 3, (steps, *self.batch_size), device=self.device)

    def _forcing(self, action: Tensor) -> Tensor:
        """The torque of each action (gymnasium's ``AVAIL_TORQUE[action]``)."""
        return self.available_torque[self._per_env(action)]

    def _dynamics(self, state: Tensor, forcing: Tensor) -> Tensor:
        state = self._rk4(state, forcing)
        self._wrap_angles_(state[:2])
        state[2:].clamp_(self.min_velocity, self.max_velocity)
        return state

    def _terminated(self, new_state: Tensor) -> Tensor:
        """gymnasium's ``_terminal``: the tip above the bar, -cos θ1 - cos(θ1 + θ2) > 1."""
        return -new_state[0].cos() - (new_state[0] + new_state[1]).cos() > 1.0

    def _reward(self, state: Tensor, action: Tensor, new_state: Tensor) -> Tensor:
        """0 when the step terminates, -1 otherwise."""
        return self._terminated(new_state).to(self.dtype) - 1.0
