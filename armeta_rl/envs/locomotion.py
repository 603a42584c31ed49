"""Locomotion task families, batched over ``[tasks, episodes]`` on gymnasium's v5 MuJoCo models:
the planar HalfCheetah-Vel and HalfCheetah-Dir (MAML, Finn et al. 2017, Sec. 5.3) and
Walker2d-Vel (the velocity half of MPTS's Walker2d-MassVel, Wang et al. 2025), and the Ant's
Ant-Dir (ProMP); the Ant's goal family is :class:`~armeta_rl.envs.ant_goal.AntGoalEnv`.

Each robot is planar: its root is an x slider, a z slider and a pitch hinge (``qpos[0:3]``), and
its forward velocity over an env step is ``v = (x' − x) / dt``, with ``x = qpos[0]`` before and
``x'`` after the step and ``dt = frame_skip · timestep``. With ``a`` the action as given (MuJoCo
clamps the applied control to [-1, 1]), the rewards are

    HalfCheetah-Vel   r = −|v − v_goal| − 0.05‖a‖²        pytorch-maml-rl's HalfCheetahVelEnv
                                                          (cbfinn/maml_rl half_cheetah_env_rand.py)
    HalfCheetah-Dir   r = d · v − 0.05‖a‖², d = ±1        pytorch-maml-rl's HalfCheetahDirEnv
                                                          (half_cheetah_env_rand_direc.py)
    Walker2d-Vel      r = −|v − v_goal| − 0.05‖a‖² + 1    MPTS's Walker2dMassVelEnv (thu-rllab/MPTS,
                                                          MetaRL/envs/mujoco/walker2d.py)

(0.05 is the references' ``0.5 * 1e-1``, ``ctrl_cost_weight`` here; Walker2d's 1 is its alive
bonus, given every step). No episode terminates (the references' ``done = False``; gymnasium's
HalfCheetah never terminates, and MPTS turned Walker2d's health check off) unless its state
turns non-finite; episodes are truncated after ``max_steps`` (200, MAML's horizon and MPTS's
time limit).

Observation (20 values), as the references' ``_get_obs``: ``qpos[1:]`` (root height, pitch and
the 6 joint angles), ``qvel`` (Walker2d: clipped to ±10), and the torso position ``xpos`` (3).
The references read ``xpos`` right after ``mj_step``, where it still describes the start of the
last substep; here it is the torso's position at the new state, as forward kinematics after the
step computes it (and as :class:`~armeta_rl.envs.ant_goal.AntGoalEnv` reads it), taken from the
root sliders' qpos in MuJoCo's own operations. The dynamics are ``mj_step``'s exactly.

Models: ``half_cheetah.xml`` (HalfCheetah-v5: time step 0.01 s, frame skip 5, dt = 0.05 s) and
``walker2d_v5.xml`` (Walker2d-v5, both feet of friction 1.9: time step 0.002 s, frame skip 4,
dt = 0.008 s). Reset as gymnasium's: ``qpos0 + U(±s)`` and, for HalfCheetah, ``s·N(0, 1)``
velocities (s = 0.1), for Walker2d ``U(±s)`` velocities (s = 0.005).

Task identifiers (``"params"``, :data:`~armeta_rl.tasks.TASK_KEY`; the protocol of
:mod:`armeta_rl.envs.batched_mujoco`): ``goal_velocity`` (any finite value; the references draw
it from U(0, 2)) or ``direction`` in [-1, 1]. HalfCheetah-Dir is a discrete-valued family
read from a continuous identifier: the direction is ``d = +1`` where ``direction ≥ 0`` and
``d = −1`` below, so p0 uniform on [-1, 1] is the references' Bernoulli(½) over {−1, +1}, and a
density over [-1, 1] (an adversary's) weighs the two directions by its mass on each half. The
mass-scale families (HalfCheetah-MassVel, Walker2d-MassVel) add MPTS's mass scale on top with a
:class:`~armeta_rl.envs.mujoco_tasks.PhysicsTaskTransform` (``configs/benchmark/``).

One departure from pytorch-maml-rl: its configs wrap the env in a ``NormalizedActionWrapper``
of scale 10 (the control is ``clip(a / 10, −1, 1)`` and the cost is on that control), while here,
as in cbfinn/maml_rl, gymnasium and :class:`~armeta_rl.envs.ant_goal.AntGoalEnv`, the policy's
action is the control.

Ant-Dir: the MuJoCo Ant must run in a hidden direction of the plane (ProMP's
``AntRandDirec2DEnv``, Rothfuss et al. 2018, as learn2learn's ``AntDirectionEnv``), batched over
``[tasks, episodes]``.

The task is an angle θ (identifier ``direction_angle``, radians, any finite value; the references
draw the direction uniformly on the unit circle, i.e. θ ~ U[-π, π]) and its direction
``u = (cos θ, sin θ)``. The reward of a step, with ``Δxy`` the torso's displacement over the step,
``dt = frame_skip · 0.01 s``, ``a`` the action as given and ``F = clip(cfrc_ext, -1, 1)``, is the
references':

    r = u · Δxy / dt                           velocity along the direction
        - ctrl_cost_weight · ‖a‖²              default 0.5 (ProMP / learn2learn)
        - contact_cost_weight · ‖F‖²           default 0.0005 (= 0.5·1e-3)
        + survive_reward                       default 1.0, every step

and an episode terminates when the state is non-finite or the torso height leaves
``healthy_z_range`` = [0, 1] (the references' ``1.0 >= z >= 0``). The references take ``Δxy``
from the torso's ``xpos`` read right after each ``mj_step`` (the start of its last substep); here
it is the exact displacement of the torso, whose free joint makes ``xpos = qpos[0:3]``.

Model, dynamics, observation (119 values, torso position included; ProMP's leaves out
``qpos[0:2]``, the xmat and the xpos) and throughput are those of the Ant of
:class:`~armeta_rl.envs.ant_goal.AntTaskEnv`; pytorch-maml-rl's Ant-Dir is the 1-D case
(θ ∈ {0, π}) with its Ant-Pos weights.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import mujoco
import numpy as np
import torch

from armeta_rl.envs.ant_goal import AntTaskEnv
from armeta_rl.envs.batched_mujoco import (
    STAGE_NONE,
    BatchedMujocoEnv,
    check_arguments,
    common_checks,
    load_gym_model,
)

TORSO = "torso"


class PlanarRunnerEnv(BatchedMujocoEnv):
    """A planar runner of gymnasium (root x, z, pitch; see the module docstring), its 20-value
    observation and its forward velocity; a subclass sets the model (:attr:`xml`), the
    identifiers and the reward.

    Args:
        batch_size, max_steps, frame_skip, reset_noise_scale, threads, seed, device: as
            :class:`~armeta_rl.envs.batched_mujoco.BatchedMujocoEnv`.
        ctrl_cost_weight: weight of ``‖a‖²`` in the reward.
    """

    xml: str = ""
    velocity_clip: float = np.inf  # |qvel| observed at most (Walker2d: 10)
    stage = STAGE_NONE  # the torso's xpos is the root sliders' qpos (_torso_position)
    torso_from_qpos = True
    """The torso's position is computed from the root's qpos (:meth:`_torso_position`, with no
    forward kinematics after a step), or, where ``False`` (MuJoCo Warp), read from the
    simulations' ``xpos`` after forward kinematics at the new state (``stage = STAGE_POS``)."""
    alive_bonus: float = 0.0  # reward for every step (Walker2d: 1)

    def __init__(
        self,
        batch_size: Sequence[int],
        max_steps: int,
        frame_skip: int,
        ctrl_cost_weight: float,
        reset_noise_scale: float,
        threads: int | None,
        seed: int | None,
        device: torch.device | str,
        require_identifiers: bool,
    ) -> None:
        check_arguments({
            **common_checks(max_steps, frame_skip, reset_noise_scale, threads),
            "ctrl_cost_weight": (ctrl_cost_weight, ctrl_cost_weight >= 0, "must be >= 0"),
        })
        self.ctrl_cost_weight = float(ctrl_cost_weight)
        model = load_gym_model(self.xml)
        self._torso = model.body(TORSO).id
        self._torso_origin, self._sliders = planar_root(model, self._torso)
        super().__init__(model, batch_size, max_steps, frame_skip, reset_noise_scale, threads,
                         seed, device, require_identifiers)

    def observation_size(self) -> int:
        return self.model.nq - 1 + self.model.nv + 3

    def _bind_outputs(self) -> None:
        if not self.torso_from_qpos:
            self._xpos = self.sim.bind("xpos")

    def _observe(self) -> np.ndarray:
        """Fill the observation buffer ``[n_sims, 20]``: qpos[1:], clipped qvel, torso xpos."""
        nq, nv, obs = self.model.nq, self.model.nv, self._obs
        obs[:, : nq - 1] = self._qpos[:, 1:]
        obs[:, nq - 1 : nq - 1 + nv] = self._qvel.clip(-self.velocity_clip, self.velocity_clip)
        obs[:, nq - 1 + nv :] = (self._torso_position() if self.torso_from_qpos
                                 else self._xpos[:, self._torso])
        return obs

    def _torso_position(self) -> np.ndarray:
        """The torso's world position ``[n_sims, 3]`` at the current qpos, as MuJoCo's forward
        kinematics computes it (``mj_kinematics``): the torso's body position moved by the x
        slider, then by the z slider, each along its unit axis by its qpos less its qpos0 (the
        pitch hinge turns the torso about its own origin, which it leaves in place). The same
        floating-point operations, so the same bits (``tests/test_locomotion.py``), without a
        kinematics pass over every body after each step."""
        qpos, qpos0 = self._qpos, self.model.qpos0
        position = self._torso_origin
        for address, axis in self._sliders:
            position = position + axis * (qpos[:, address : address + 1] - qpos0[address])
        return position

    def forward_velocity(self, qpos_before: np.ndarray) -> np.ndarray:
        """``(x' − x) / dt`` ``[n_sims]``: the root's mean forward velocity over the step."""
        return (self._qpos[:, 0] - qpos_before[:, 0]) / self.dt

    def ctrl_cost(self, action: np.ndarray) -> np.ndarray:
        """``ctrl_cost_weight · ‖a‖²`` ``[n_sims]``."""
        return self.ctrl_cost_weight * self.xp.square(action).sum(-1)

    def _reward(self, action: np.ndarray, qpos_before: np.ndarray,
                task: np.ndarray) -> np.ndarray:
        """The task's term (the subclass's :meth:`_forward_reward`) − ``ctrl_cost_weight·‖a‖²`` +
        :attr:`alive_bonus`."""
        return self._forward_reward(qpos_before, task) - self.ctrl_cost(action) + self.alive_bonus


def planar_root(model: mujoco.MjModel, torso: int
                ) -> tuple[np.ndarray, list[tuple[int, np.ndarray]]]:
    """The torso's body position and its root sliders (qpos address, unit axis), of a planar
    runner whose torso hangs from the world by an x slider, a z slider and a pitch hinge at its
    origin (the module docstring), the structure :meth:`PlanarRunnerEnv._torso_position` reads;
    ``ValueError`` for a model of another."""
    joints = range(model.body_jntadr[torso], model.body_jntadr[torso] + model.body_jntnum[torso])
    kinds = [int(model.jnt_type[j]) for j in joints]
    sliders = [(int(model.jnt_qposadr[j]), model.jnt_axis[j].copy()) for j in joints[:2]]
    slide, hinge = mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE
    unrotated = np.array_equal(model.body_quat[torso], [1, 0, 0, 0])
    hinge_at_origin = not model.jnt_pos[joints[2]].any()
    axes = [axis.tolist() for _, axis in sliders]
    if (model.body_parentid[torso] != 0 or not unrotated or kinds != [slide, slide, hinge]
            or not hinge_at_origin or axes != [[1, 0, 0], [0, 0, 1]]):
        raise ValueError("the torso is not a planar runner's root (x slider, z slider, pitch "
                         "hinge at its origin, hanging from the world unrotated)")
    return model.body_pos[torso].copy(), sliders


def constant_speed_goal_term(goal_velocity: torch.Tensor, steps: int) -> torch.Tensor:
    """R_blind ``[K]`` of target velocities ``[K]``: −T·|c − v_goal|, the goal term (the summed
    −|v − v_goal|) of running at the constant speed c from the first of T steps, with c the
    batch's median target, the constant that minimizes the batch's mean |c − v_goal|: the best
    goal-blind policy of the family's goal term. A bound (no runner is at speed c from its first
    step), so the share of the goal-blind gap an adapted policy closes, measured against it, is
    conservative."""
    target = goal_velocity.to(torch.float64)
    return -steps * (target.median() - target).abs()


class TargetVelocity:
    """The velocity task of HalfCheetah-Vel and Walker2d-Vel: a hidden target velocity
    ``goal_velocity`` ∈ [0, 2] m/s (drawn from U(0, 2) where never set), reward term
    ``−|v − goal_velocity|``, reported after every step as ``"reward_forward"``; its goal-blind
    reference is the best constant speed (:meth:`blind_goal_term`)."""

    identifier_names = ("goal_velocity",)
    task_boxes = {"goal_velocity": (0.0, 2.0)}

    @staticmethod
    def blind_goal_term(params: torch.Tensor, steps: int) -> torch.Tensor:
        """R_blind ``[K]`` of the tasks ``params`` ``[K, d]`` (the target velocity first, as
        any physics parameter comes after the env's own identifiers) over ``steps`` steps:
        :func:`constant_speed_goal_term`."""
        return constant_speed_goal_term(params[..., 0], steps)

    def _default_identifiers(self) -> torch.Tensor:
        return 2 * torch.rand(*self.batch_size, 1, generator=self._generator, dtype=torch.float64)

    def _forward_reward(self, qpos_before: np.ndarray, task: np.ndarray) -> np.ndarray:
        """−|v − goal_velocity| ``[n_sims]``."""
        return -self.xp.abs(self.forward_velocity(qpos_before) - task[:, 0])


class HalfCheetahTaskEnv(PlanarRunnerEnv):
    """gymnasium's HalfCheetah as a planar runner with its defaults; :class:`HalfCheetahVelEnv`
    and :class:`HalfCheetahDirEnv` add the task.

    Args:
        batch_size: ``[tasks, episodes]`` (any batch shape works).
        max_steps: time limit in env steps (200).
        frame_skip: physics steps per env step (5, as gymnasium's HalfCheetah).
        ctrl_cost_weight: 0.05 (pytorch-maml-rl's ``0.5 * 1e-1``).
        reset_noise_scale: initial qpos = qpos0 + U(±scale), qvel = scale·N(0, 1).
        threads: threads stepping the MuJoCo batch natively (1: the calling thread only;
            ``None``: one per CPU core).
        seed: seed of the generator for reset noise and default identifiers.
        device: torch device of the outputs (the physics runs on the CPU).
    """

    xml = "half_cheetah.xml"

    def __init__(
        self,
        batch_size: Sequence[int] = (1, 1),
        max_steps: int = 200,
        frame_skip: int = 5,
        ctrl_cost_weight: float = 0.05,
        reset_noise_scale: float = 0.1,
        threads: int | None = 1,
        seed: int | None = None,
        device: torch.device | str = "cpu",
        require_identifiers: bool = False,
    ) -> None:
        super().__init__(batch_size, max_steps, frame_skip, ctrl_cost_weight, reset_noise_scale,
                         threads, seed, device, require_identifiers)


class HalfCheetahVelEnv(TargetVelocity, HalfCheetahTaskEnv):
    """HalfCheetah-Vel: run at a hidden target velocity; reward ``−|v − goal_velocity| −
    ctrl_cost_weight·‖a‖²`` (module docstring). Arguments as :class:`HalfCheetahTaskEnv`;
    velocities never set are drawn from U(0, 2).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import HalfCheetahVelEnv
        >>> from armeta_rl.tasks import TASK_KEY
        >>> env = HalfCheetahVelEnv(batch_size=(2, 1), seed=0)  # 2 tasks x 1 episode
        >>> goal = torch.tensor([[1.5], [0.0]])[:, None]  # run at 1.5 m/s; stand
        >>> start = env.reset(TensorDict({TASK_KEY: goal}, [2, 1]))
        >>> idle = lambda td: td.set("action", torch.zeros(2, 1, 6))  # no control cost
        >>> steps = env.rollout(3, idle, tensordict=start, auto_reset=False)
        >>> steps["next", "reward"].squeeze(-1).round(decimals=2)  # idle: -1.5 asked to run
        tensor([[[-1.5700, -1.5500, -1.5100]],
        <BLANKLINE>
                [[-0.1500, -0.1500, -0.0800]]])
        >>> x = torch.cat([start["observation"][..., None, 17],  # the torso's x
        ...                steps["next", "observation"][..., 17]], -1)
        >>> (-(x.diff() / 0.05 - goal).abs()).round(decimals=2)  # -|v - goal|, dt = 0.05 s
        tensor([[[-1.5700, -1.5500, -1.5100]],
        <BLANKLINE>
                [[-0.1500, -0.1500, -0.0800]]])
    """


class HalfCheetahDirEnv(HalfCheetahTaskEnv):
    """HalfCheetah-Dir: run forward or backward; reward ``d·v − ctrl_cost_weight·‖a‖²`` with
    ``d = +1`` where the identifier ``direction ≥ 0``, else ``−1`` (module docstring). Arguments
    as :class:`HalfCheetahTaskEnv`; directions never set are ±1 with probability ½ each.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import HalfCheetahDirEnv
        >>> from armeta_rl.tasks import TASK_KEY
        >>> def rewards(direction):  # the same seed: the same start and the same motion
        ...     env = HalfCheetahDirEnv(batch_size=(1, 1), seed=0)
        ...     start = env.reset(TensorDict({TASK_KEY: torch.tensor([[[direction]]])}, [1, 1]))
        ...     idle = lambda td: td.set("action", torch.zeros(1, 1, 6))  # no control cost
        ...     steps = env.rollout(3, idle, tensordict=start, auto_reset=False)
        ...     return steps["next", "reward"].flatten().round(decimals=2)
        >>> rewards(1.0), rewards(-0.3)  # d·v: a backward drift, d = +1, then d = -1 (< 0)
        (tensor([-0.0600, -0.0700, -0.2100]), tensor([0.0600, 0.0700, 0.2100]))
    """

    identifier_names = ("direction",)
    identifier_low, identifier_high = -1.0, 1.0
    task_boxes = {"direction": (-1.0, 1.0)}

    def _default_identifiers(self) -> torch.Tensor:
        unit = torch.rand(*self.batch_size, 1, generator=self._generator, dtype=torch.float64)
        return torch.where(unit < 0.5, -1.0, 1.0).to(torch.float64)

    def _forward_reward(self, qpos_before: np.ndarray, task: np.ndarray) -> np.ndarray:
        """``d·v`` ``[n_sims]``."""
        return self.xp.where(task[:, 0] >= 0, 1.0, -1.0) * self.forward_velocity(qpos_before)


class Walker2dVelEnv(TargetVelocity, PlanarRunnerEnv):
    """Walker2d-Vel (MPTS): walk at a hidden target velocity; reward ``−|v − goal_velocity| −
    ctrl_cost_weight·‖a‖² + alive_bonus`` (module docstring), no termination. Batch size
    ``[tasks, episodes]``.

    Args:
        batch_size: ``[tasks, episodes]`` (any batch shape works).
        max_steps: time limit in env steps (200, MPTS's).
        frame_skip: physics steps per env step (4, as gymnasium's Walker2d).
        ctrl_cost_weight: 0.05 (MPTS's ``0.5 * 1e-1``).
        alive_bonus: reward added every step (1, MPTS's).
        reset_noise_scale: initial qpos = qpos0 + U(±scale), qvel = U(±scale) (0.005).
        threads: threads stepping the MuJoCo batch natively (1: the calling thread only;
            ``None``: one per CPU core).
        seed: seed of the generator for reset noise and default velocities (U(0, 2)).
        device: torch device of the outputs (the physics runs on the CPU).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import Walker2dVelEnv
        >>> from armeta_rl.tasks import TASK_KEY
        >>> env = Walker2dVelEnv(batch_size=(2, 1), seed=0)  # 2 tasks x 1 episode
        >>> goal = torch.tensor([[1.5], [0.0]])[:, None]  # walk at 1.5 m/s; stand
        >>> start = env.reset(TensorDict({TASK_KEY: goal}, [2, 1]))
        >>> idle = lambda td: td.set("action", torch.zeros(2, 1, 6))  # no control cost
        >>> steps = env.rollout(3, idle, tensordict=start, auto_reset=False)
        >>> steps["next", "reward"].squeeze(-1).round(decimals=2)  # standing earns the bonus 1
        tensor([[[-0.5000, -0.5000, -0.5000]],
        <BLANKLINE>
                [[ 1.0000,  1.0000,  1.0000]]])
        >>> x = torch.cat([start["observation"][..., None, 17],  # the torso's x
        ...                steps["next", "observation"][..., 17]], -1)
        >>> (1 - (x.diff() / 0.008 - goal).abs()).round(decimals=2)  # dt = 4 · 0.002 s
        tensor([[[-0.5000, -0.5000, -0.5000]],
        <BLANKLINE>
                [[ 1.0000,  1.0000,  1.0000]]])
    """

    xml = "walker2d_v5.xml"
    velocity_clip = 10.0

    def __init__(
        self,
        batch_size: Sequence[int] = (1, 1),
        max_steps: int = 200,
        frame_skip: int = 4,
        ctrl_cost_weight: float = 0.05,
        alive_bonus: float = 1.0,
        reset_noise_scale: float = 5e-3,
        threads: int | None = 1,
        seed: int | None = None,
        device: torch.device | str = "cpu",
        require_identifiers: bool = False,
    ) -> None:
        self.alive_bonus = float(alive_bonus)
        super().__init__(batch_size, max_steps, frame_skip, ctrl_cost_weight, reset_noise_scale,
                         threads, seed, device, require_identifiers)

    def _reset_noise(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """gymnasium's Walker2d: U(±s) on both qpos and qvel."""
        scale, gen = self.reset_noise_scale, self._generator
        qpos = scale * (2 * torch.rand(n, self.model.nq, generator=gen, dtype=torch.float64) - 1)
        qvel = scale * (2 * torch.rand(n, self.model.nv, generator=gen, dtype=torch.float64) - 1)
        return qpos, qvel


class AntDirEnv(AntTaskEnv):
    """MuJoCo Ant running in the direction ``direction_angle``, batch size ``[tasks, episodes]``;
    see the module docstring (Ant-Dir).

    Args:
        batch_size: ``[tasks, episodes]`` (any batch shape works).
        max_steps: time limit in env steps (200).
        frame_skip: physics steps per env step (5, as gymnasium's Ant).
        ctrl_cost_weight: weight of the control cost (module docstring).
        contact_cost_weight: weight of the contact cost (module docstring).
        survive_reward: reward per step alive (module docstring).
        healthy_z_range: torso heights outside this closed interval terminate the episode.
        reset_noise_scale: initial qpos = model qpos0 + U(±scale), qvel = scale·N(0, 1).
        threads: threads stepping the MuJoCo batch natively (1: the calling thread only;
            ``None``: one per CPU core).
        seed: seed of the generator for reset noise and default angles (U[-π, π]).
        device: torch device of the outputs (the physics runs on the CPU).
        require_identifiers: refuse a full reset without identifiers (see
            :class:`~armeta_rl.envs.batched_mujoco.BatchedMujocoEnv`).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import AntDirEnv
        >>> from armeta_rl.tasks import TASK_KEY
        >>> def walk(angle):  # the same seed: the same start and the same motion
        ...     env = AntDirEnv(batch_size=(1, 1), seed=0)
        ...     start = env.reset(TensorDict({TASK_KEY: torch.tensor([[[angle]]])}, [1, 1]))
        ...     idle = lambda td: td.set("action", torch.zeros(1, 1, 8))  # no control cost
        ...     return start, env.rollout(2, idle, tensordict=start, auto_reset=False)
        >>> start, east = walk(0.0)
        >>> _, west = walk(torch.pi)
        >>> ((east["next", "reward"] - west["next", "reward"]) / 2).flatten()  # u·v of u = ±x
        tensor([-0.1513, -0.1305])
        >>> x = torch.cat([start["observation"][..., None, 0], east["next", "observation"][..., 0]],
        ...               -1)  # the torso's x
        >>> (x.diff() / 0.05).flatten()  # its velocity over dt = 5 · 0.01 s
        tensor([-0.1513, -0.1305])
    """

    identifier_names = ("direction_angle",)
    task_boxes = {"direction_angle": (-math.pi, math.pi)}

    def __init__(
        self,
        batch_size: Sequence[int] = (1, 1),
        max_steps: int = 200,
        frame_skip: int = 5,
        ctrl_cost_weight: float = 0.5,
        contact_cost_weight: float = 5e-4,
        survive_reward: float = 1.0,
        healthy_z_range: Sequence[float] = (0.0, 1.0),
        reset_noise_scale: float = 0.1,
        threads: int | None = 1,
        seed: int | None = None,
        device: torch.device | str = "cpu",
        require_identifiers: bool = False,
    ) -> None:
        super().__init__(batch_size, max_steps, frame_skip, ctrl_cost_weight, contact_cost_weight,
                         survive_reward, healthy_z_range, reset_noise_scale, threads, seed, device,
                         require_identifiers=require_identifiers)

    def _default_identifiers(self) -> torch.Tensor:
        unit = torch.rand(*self.batch_size, 1, generator=self._generator, dtype=torch.float64)
        return torch.pi * (2 * unit - 1)

    def _reward(self, action: np.ndarray, qpos_before: np.ndarray,
                task: np.ndarray) -> np.ndarray:
        """The Ant-Dir reward of the module docstring."""
        xp = self.xp
        direction = xp.stack([xp.cos(task[:, 0]), xp.sin(task[:, 0])], -1)
        velocity = (self._qpos[:, :2] - qpos_before[:, :2]) / self.dt
        return self.ant_reward((direction * velocity).sum(-1), action)
