"""Ant goal-position task ("Ant-Pos", the paper's second meta-RL benchmark; pytorch-maml-rl and
CAVIA's ``AntPos``) on the maintained ``mujoco`` bindings, batched over ``[tasks, episodes]``.

The MuJoCo Ant that ships with gymnasium (``gymnasium/envs/mujoco/assets/ant.xml``: RK4, time step
0.01 s, 8 motors of gear 150 with controls in [-1, 1]) must walk its torso to a hidden goal
``g ∈ R²``. One env step applies the action for ``frame_skip`` (5, as gymnasium's Ant) physics
steps. The reward of a step, with ``a`` the action as given (MuJoCo clamps the applied control to
[-1, 1]) and ``F = clip(cfrc_ext, -1, 1)`` the external (contact) forces of all bodies, is

    r = -‖torso_xy - g‖₁                       goal term (L1, as pytorch-maml-rl's AntPos)
        - ctrl_cost_weight · ‖a‖²              default 0.005 (= 0.5·1e-2, pytorch-maml-rl's Ant)
        - contact_cost_weight · ‖F‖²           default 0.0005 (= 0.5·1e-3, gymnasium/rllab Ant)
        + survive_reward                       default 0.05 (pytorch-maml-rl's Ant), every step

An episode terminates when the state (qpos, qvel) is non-finite or the torso height leaves
``healthy_z_range`` = [0.2, 1.0], and is truncated after ``max_steps`` (200) steps. The goal term
is also reported after every step as ``"reward_forward"``, so that the episodes carry the goal's
own part of their return (:func:`standing_goal_term` is its goal-blind reference).

Observation (119 values, float in the default torch dtype), all evaluated at the state *after* the
step (``mj_forward`` then ``mj_rnePostConstraint``, so the contact forces are real, not zeros):

    [0:15]    qpos: torso x, y, z, torso quaternion (w, x, y, z), 8 joint angles
    [15:29]   qvel: torso linear (3) and angular (3) velocity, 8 joint velocities
    [29:107]  clip(cfrc_ext, -1, 1) of the 13 bodies after the world (6 each: torque, force);
              the world's row is always zero and is left out, as in gymnasium's Ant-v5
    [107:116] torso orientation, its 3×3 rotation matrix ``xmat`` row-major
    [116:119] torso position ``xpos`` (equal to qpos[0:3])

The goal is not observed. gymnasium reads ``xpos`` and ``cfrc_ext`` right after ``mj_step``, when
they still describe the last Runge-Kutta stage rather than the new state (gymnasium's Ant-v5
changelog); here they are recomputed at the new state. The dynamics (qpos, qvel) are those of
``mj_step`` exactly.

Throughput and the task protocol are those of every batched MuJoCo env
(:mod:`armeta_rl.envs.batched_mujoco`): all ``tasks × episodes`` simulations step natively in one
:class:`mujoco.batch.Batch`. ``mj_rnePostConstraint`` runs inside its step call because the model
gets one accelerometer sensor on the torso, which makes MuJoCo's sensor stage compute
``cfrc_ext``; the sensor changes nothing else.

Goals are passed as ``"params"`` (:data:`~armeta_rl.tasks.TASK_KEY`, ``[*batch, 2]``: goal_x,
goal_y) in the reset TensorDict and kept across automatic (partial) resets; goals never set are
drawn uniformly from ``[-goal_range, goal_range]²`` with the env's seeded generator. Goals under
another key (``"goal"``), of another width or not finite raise
:class:`~armeta_rl.errors.IdentifierError`.

:class:`AntTaskEnv` is the Ant every Ant task shares (model, observation, contact forces,
termination); :class:`AntGoalEnv` adds the goal, :class:`~armeta_rl.envs.locomotion.AntDirEnv` a
direction.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import mujoco
import numpy as np
import torch

from armeta_rl.envs.batched_mujoco import (
    GYM_ASSETS,
    STAGE_ACC,
    BatchedMujocoEnv,
    check_arguments,
    common_checks,
)

ANT_XML = os.path.join(GYM_ASSETS, "ant.xml")
TORSO = "torso"
GOAL_NAMES = ("goal_x", "goal_y")


def load_ant_model(with_force_sensor: bool = True) -> mujoco.MjModel:
    """gymnasium's Ant model; with ``with_force_sensor`` an accelerometer on the torso is added so
    that every forward pass runs ``mj_rnePostConstraint`` (fills ``cfrc_ext``)."""
    spec = mujoco.MjSpec.from_file(ANT_XML)
    if with_force_sensor:
        spec.body(TORSO).add_site(name="torso_rne")
        spec.add_sensor(
            type=mujoco.mjtSensor.mjSENS_ACCELEROMETER,
            objtype=mujoco.mjtObj.mjOBJ_SITE,
            objname="torso_rne",
        )
    return spec.compile()


def observation_size(model: mujoco.MjModel) -> int:
    """Length of the observation vector (119 for gymnasium's Ant)."""
    return model.nq + model.nv + 6 * (model.nbody - 1) + 9 + 3


class AntTaskEnv(BatchedMujocoEnv):
    """The MuJoCo Ant of every Ant task, batched over ``[tasks, episodes]``: gymnasium's model
    with a torso accelerometer (:func:`load_ant_model`), the 119-value observation, the terms of
    the reward every Ant task shares (control and contact costs, survival reward) and termination
    outside ``healthy_z_range`` (module docstring). A subclass adds the task: its identifiers and
    the task term of its reward.

    Args:
        batch_size, max_steps, frame_skip, reset_noise_scale, threads, seed, device: as
            :class:`~armeta_rl.envs.batched_mujoco.BatchedMujocoEnv`.
        ctrl_cost_weight, contact_cost_weight, survive_reward: the shared reward terms
            (:meth:`ant_reward`).
        healthy_z_range: torso heights outside this closed interval terminate the episode.
        checks: further argument checks of the subclass (``{name: (value, ok, allowed)}``).
    """

    stage = STAGE_ACC  # mj_forward and, through the torso sensor, mj_rnePostConstraint

    def __init__(
        self,
        batch_size: Sequence[int],
        max_steps: int,
        frame_skip: int,
        ctrl_cost_weight: float,
        contact_cost_weight: float,
        survive_reward: float,
        healthy_z_range: Sequence[float],
        reset_noise_scale: float,
        threads: int | None,
        seed: int | None,
        device: torch.device | str,
        checks: dict[str, tuple[object, bool, str]] | None = None,
        require_identifiers: bool = False,
    ) -> None:
        check_arguments({
            **common_checks(max_steps, frame_skip, reset_noise_scale, threads),
            "healthy_z_range": (
                healthy_z_range,
                len(healthy_z_range) == 2 and healthy_z_range[0] < healthy_z_range[1],
                "[low, high] with low < high",
            ),
            **(checks or {}),
        })
        self.ctrl_cost_weight = float(ctrl_cost_weight)
        self.contact_cost_weight = float(contact_cost_weight)
        self.survive_reward = float(survive_reward)
        self.healthy_z_range = (float(healthy_z_range[0]), float(healthy_z_range[1]))
        model = load_ant_model()
        self._torso = model.body(TORSO).id
        super().__init__(model, batch_size, max_steps, frame_skip, reset_noise_scale, threads,
                         seed, device, require_identifiers)

    def observation_size(self) -> int:
        return observation_size(self.model)

    def _bind_outputs(self) -> None:
        self._cfrc_ext, self._xpos, self._xmat = (
            self.sim.bind(k) for k in ("cfrc_ext", "xpos", "xmat")
        )
        self._forces = self._cfrc_ext.clip(-1.0, 1.0)  # the clipped forces, refilled every step

    # _observe, ant_reward, _healthy and AntGoalEnv._reward read the bound arrays with operators
    # and methods that NumPy arrays and torch tensors share: the same code serves the CPU batch
    # (float64 NumPy) and MuJoCo Warp (float32 torch on its device, ant_goal_warp).

    def _observe(self) -> np.ndarray:
        """Fill the observation buffer ``[n_sims, 119]`` and the clipped forces from the batch."""
        nq, nv, n = self.model.nq, self.model.nv, self.n_sims
        obs = self._obs
        self._forces[...] = self._cfrc_ext.clip(-1.0, 1.0)
        obs[:, :nq] = self._qpos
        obs[:, nq : nq + nv] = self._qvel
        end = obs.shape[1] - 12
        obs[:, nq + nv : end] = self._forces[:, 1:].reshape(n, -1)
        obs[:, end : end + 9] = self._xmat[:, self._torso]
        obs[:, end + 9 :] = self._xpos[:, self._torso]
        return obs

    def ant_reward(self, task_term: np.ndarray, action: np.ndarray) -> np.ndarray:
        """``task_term − ctrl_cost_weight·‖a‖² − contact_cost_weight·‖F‖² + survive_reward``
        ``[n_sims]``, with ``F`` the clipped contact forces after the step."""
        return (
            task_term
            - self.ctrl_cost_weight * (action * action).sum(-1)
            - self.contact_cost_weight * (self._forces * self._forces).sum((-2, -1))
            + self.survive_reward
        )

    def _healthy(self) -> np.ndarray:
        state = self._obs[:, : self.model.nq + self.model.nv]
        height = self._qpos[:, 2]
        low, high = self.healthy_z_range
        return (abs(state) < math.inf).all(-1) & (height >= low) & (height <= high)


def standing_goal_term(goal: torch.Tensor, steps: int) -> torch.Tensor:
    """R_blind ``[K]`` of goals ``[K, 2]``: −T·‖m − goal‖₁, the goal term (the summed
    −‖xy − goal‖₁) of a torso standing at m from the first of T steps, with m the goals'
    coordinate-wise median, the point that minimizes the batch's mean L1 distance: the best
    goal-blind policy of the goal term. A bound (the reference teleports to m; with the oracle's
    0, standing on the goal from the first step, both ends of the gap are), so the share of the
    goal-blind gap an adapted policy closes, measured against it, is conservative."""
    goal = goal.to(torch.float64)
    return -steps * (goal - goal.median(0).values).abs().sum(-1)


class AntGoalEnv(AntTaskEnv):
    """MuJoCo Ant goal-position env with batch size ``[tasks, episodes]``; see the module docstring.

    Args:
        batch_size: ``[tasks, episodes]`` (any batch shape works).
        max_steps: time limit in env steps (200); reaching it sets ``"truncated"``.
        frame_skip: physics steps per env step (5, as gymnasium's Ant).
        ctrl_cost_weight: weight of the control cost (module docstring).
        contact_cost_weight: weight of the contact cost (module docstring).
        survive_reward: reward per step alive (module docstring).
        healthy_z_range: torso heights outside this closed interval terminate the episode.
        reset_noise_scale: initial qpos = model qpos0 + U(±scale), qvel = scale·N(0, 1).
        goal_range: default goals (never set by a reset) are U([-goal_range, goal_range]²).
        threads: threads stepping the MuJoCo batch natively (1: the calling thread only;
            ``None``: one per CPU core).
        seed: seed of the generator for reset noise and default goals.
        device: torch device of the outputs (the physics runs on the CPU).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import AntGoalEnv
        >>> from armeta_rl.tasks import TASK_KEY
        >>> env = AntGoalEnv(batch_size=(2, 1), seed=0)  # 2 tasks x 1 episode
        >>> goal = torch.tensor([[1.0, -2.0], [0.0, 0.0]])[:, None]  # the ant starts near 0
        >>> start = env.reset(TensorDict({TASK_KEY: goal}, [2, 1]))
        >>> idle = lambda td: td.set("action", torch.zeros(2, 1, 8))
        >>> steps = env.rollout(2, idle, tensordict=start, auto_reset=False)
        >>> steps["next", "reward_forward"].squeeze(-1).round(decimals=2)  # the goal term
        tensor([[[-3.0200, -3.0200]],
        <BLANKLINE>
                [[-0.1100, -0.1000]]])
        >>> xy = steps["next", "observation"][..., :2]  # the torso's (x, y)
        >>> (-(xy - goal[:, :, None]).abs().sum(-1)).round(decimals=2)  # -‖xy - g‖₁
        tensor([[[-3.0200, -3.0200]],
        <BLANKLINE>
                [[-0.1100, -0.1000]]])
    """

    identifier_names = GOAL_NAMES
    task_boxes = {name: (-3.0, 3.0) for name in GOAL_NAMES}

    def __init__(
        self,
        batch_size: Sequence[int] = (1, 1),
        max_steps: int = 200,
        frame_skip: int = 5,
        ctrl_cost_weight: float = 5e-3,
        contact_cost_weight: float = 5e-4,
        survive_reward: float = 0.05,
        healthy_z_range: Sequence[float] = (0.2, 1.0),
        reset_noise_scale: float = 0.1,
        goal_range: float = 3.0,
        threads: int | None = 1,
        seed: int | None = None,
        device: torch.device | str = "cpu",
        require_identifiers: bool = False,
    ) -> None:
        self.goal_range = float(goal_range)
        super().__init__(batch_size, max_steps, frame_skip, ctrl_cost_weight, contact_cost_weight,
                         survive_reward, healthy_z_range, reset_noise_scale, threads, seed, device,
                         checks={"goal_range": (goal_range, goal_range > 0, "must be > 0")},
                         require_identifiers=require_identifiers)

    def _default_identifiers(self) -> torch.Tensor:
        unit = torch.rand(*self.batch_size, 2, generator=self._generator, dtype=torch.float64)
        return self.goal_range * (2 * unit - 1)

    def _reward(self, action: np.ndarray, qpos_before: np.ndarray,
                task: np.ndarray) -> np.ndarray:
        """The AntPos reward of the module docstring."""
        return self.ant_reward(self._forward_reward(qpos_before, task), action)

    def _forward_reward(self, qpos_before: np.ndarray, task: np.ndarray) -> np.ndarray:
        """The goal term −‖torso_xy − goal‖₁ ``[n_sims]``, reported after every step as
        ``"reward_forward"``."""
        xy = self._xpos[:, self._torso, :2]
        return -abs(xy - task).sum(-1)

    @staticmethod
    def blind_goal_term(params: torch.Tensor, steps: int) -> torch.Tensor:
        """R_blind ``[K]`` of the tasks ``params`` ``[K, d]`` (the goal first, as any physics
        parameter comes after the env's own identifiers) over ``steps`` steps:
        :func:`standing_goal_term`."""
        return standing_goal_term(params[..., :2], steps)
