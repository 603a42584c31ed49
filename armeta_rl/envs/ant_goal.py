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
``healthy_z_range`` = [0.2, 1.0], and is truncated after ``max_steps`` (200) steps.

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

Throughput: all ``tasks × episodes`` simulations live in one :class:`mujoco.batch.Batch`, which
steps them natively (``frame_skip`` substeps and the forward pass at the new state in one call, no
Python per simulation). ``mj_rnePostConstraint`` runs inside that call because the model gets one
accelerometer sensor on the torso, which makes MuJoCo's sensor stage compute ``cfrc_ext``; the
sensor changes nothing else. Training splits the tasks over worker processes (TorchRL
``ParallelEnv``), each owning a slice of tasks with its own batch, through
:class:`armeta_rl.collectors.parallel_episodes.TaskSplitEpisodeCollector`
(``benchmark.collector.workers``).

Goals are passed as ``"params"`` (:data:`~armeta_rl.tasks.TASK_KEY`, ``[*batch, 2]``: goal_x,
goal_y) in the reset TensorDict and kept in the env's state across automatic (partial) resets; a
reset without ``"params"`` keeps the current goals, and goals never set are drawn uniformly from
``[-goal_range, goal_range]²`` with the env's seeded generator. Goals under another key
(``"goal"``), of another width or not finite raise :class:`~armeta_rl.errors.IdentifierError`.
``"params"`` is emitted with every observation so trajectories carry their task; it is also
declared in the state spec so that resets through TorchRL transforms (``TransformedEnv`` forwards
only reset and state keys) still deliver it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import gymnasium
import mujoco
import numpy as np
import torch
from mujoco.batch import Batch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from armeta_rl.errors import ConfigError
from armeta_rl.tasks.protocol import TASK_KEY, read_identifiers

ANT_XML = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "mujoco", "assets", "ant.xml")
TORSO = "torso"
GOAL_NAMES = ("goal_x", "goal_y")
KEY = "benchmark.collector"
_ACC = mujoco.mjtStage.mjSTAGE_ACC.value
_NONE = mujoco.mjtStage.mjSTAGE_NONE.value


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


def goal_reward(xy, goal, action, forces, ctrl_cost_weight: float, contact_cost_weight: float,
                survive_reward: float):
    """The reward of the module docstring for ``n`` simulations: torso ``xy`` and ``goal``
    ``[n, 2]``, ``action`` ``[n, nu]``, clipped contact ``forces`` ``[n, nbody, 6]``. Written with
    operators and methods that NumPy arrays and torch tensors share, so the CPU env (float64
    NumPy) and the MuJoCo Warp env (float32 torch on its device) compute it with one function."""
    return (-abs(xy - goal).sum(-1)
            - ctrl_cost_weight * (action * action).sum(-1)
            - contact_cost_weight * (forces * forces).sum((-2, -1))
            + survive_reward)


def healthy(state, height, healthy_z_range: Sequence[float]):
    """Whether each simulation goes on: its state (qpos, qvel) ``[n, nq + nv]`` finite and its
    torso ``height`` ``[n]`` inside the closed ``healthy_z_range`` (NumPy or torch, as
    :func:`goal_reward`)."""
    low, high = healthy_z_range
    return (abs(state) < math.inf).all(-1) & (height >= low) & (height <= high)


def _check_arguments(max_steps: int, frame_skip: int, healthy_z_range: Sequence[float],
                     reset_noise_scale: float, goal_range: float, threads: int | None) -> None:
    """One :class:`ConfigError` line for the first bad constructor argument of the env."""
    checks = {
        f"{KEY}.max_steps": (max_steps, int(max_steps) >= 1, "must be >= 1"),
        f"{KEY}.frame_skip": (frame_skip, int(frame_skip) >= 1, "must be >= 1"),
        f"{KEY}.healthy_z_range": (
            healthy_z_range,
            len(healthy_z_range) == 2 and healthy_z_range[0] < healthy_z_range[1],
            "[low, high] with low < high",
        ),
        f"{KEY}.reset_noise_scale": (reset_noise_scale, reset_noise_scale >= 0, "must be >= 0"),
        f"{KEY}.goal_range": (goal_range, goal_range > 0, "must be > 0"),
        f"{KEY}.threads": (threads, threads is None or int(threads) >= 1,
                           "must be null (one per core) or an integer >= 1"),
    }
    for key, (value, ok, allowed) in checks.items():
        if not ok:
            raise ConfigError(key, value, allowed)


class AntGoalEnv(EnvBase):
    """MuJoCo Ant goal-position env with batch size ``[tasks, episodes]``; see the module docstring.

    Args:
        batch_size: ``[tasks, episodes]`` (any batch shape works).
        max_steps: time limit in env steps (200); reaching it sets ``"truncated"``.
        frame_skip: physics steps per env step (5, as gymnasium's Ant).
        ctrl_cost_weight, contact_cost_weight, survive_reward: reward terms (module docstring).
        healthy_z_range: torso heights outside this closed interval terminate the episode.
        reset_noise_scale: initial qpos = model qpos0 + U(±scale), qvel = scale·N(0, 1).
        goal_range: default goals (never set by a reset) are U([-goal_range, goal_range]²).
        threads: threads stepping the MuJoCo batch natively (1: the calling thread only;
            ``None``: one per CPU core).
        seed: seed of the generator for reset noise and default goals.
        device: torch device of the outputs (the physics runs on the CPU).
    """

    _has_frame_skip = True  # physics substeps run in ``_step``; no FrameSkipTransform wrapper

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
    ) -> None:
        _check_arguments(max_steps, frame_skip, healthy_z_range, reset_noise_scale, goal_range,
                         threads)
        super().__init__(device=device, batch_size=torch.Size(batch_size))
        self.max_steps, self.frame_skip = int(max_steps), int(frame_skip)
        self.ctrl_cost_weight = float(ctrl_cost_weight)
        self.contact_cost_weight = float(contact_cost_weight)
        self.survive_reward = float(survive_reward)
        self.healthy_z_range = (float(healthy_z_range[0]), float(healthy_z_range[1]))
        self.reset_noise_scale = float(reset_noise_scale)
        self.goal_range = float(goal_range)

        self.model = load_ant_model()
        self.n_sims = math.prod(self.batch_size)
        threads = (os.cpu_count() or 1) if threads is None else int(threads)
        self.sim = self._make_batch(threads)
        self._torso = self.model.body(TORSO).id
        self._qpos, self._qvel, self._ctrl = (self.sim.bind(k) for k in ("qpos", "qvel", "ctrl"))
        self._cfrc_ext, self._xpos, self._xmat = (
            self.sim.bind(k) for k in ("cfrc_ext", "xpos", "xmat")
        )
        self._forces = self._cfrc_ext.clip(-1.0, 1.0)  # the clipped forces, refilled every step
        self._obs = self._new_observation()

        self._make_specs()
        self._generator = torch.Generator()
        self._set_seed(seed)
        unit = torch.rand(*self.batch_size, 2, generator=self._generator, dtype=torch.float64)
        self._set_goal(self.goal_range * (2 * unit - 1))
        self._steps = torch.zeros(*self.batch_size, 1, dtype=torch.long, device=self.device)
        self.sim.reset()

    def _make_specs(self) -> None:
        """The TorchRL specs: observation and goal, the goal as state, the actuators' box,
        reward and done flags, all of batch shape ``batch_size``."""
        shape, dtype = self.batch_size, torch.get_default_dtype()
        low, high = self.model.actuator_ctrlrange.T
        self.observation_spec = Composite(
            {"observation": Unbounded(shape=(*shape, self._obs.shape[1]), dtype=dtype),
             TASK_KEY: Unbounded(shape=(*shape, 2), dtype=dtype)},
            shape=shape,
        )
        # The goal is also a state entry, so that TransformedEnv (which passes only reset and
        # state keys to the base env's reset) forwards it; the env's own copy stays authoritative.
        self.state_spec = Composite({TASK_KEY: Unbounded(shape=(*shape, 2), dtype=dtype)},
                                    shape=shape)
        self.action_spec = Bounded(
            torch.as_tensor(low, dtype=dtype).expand(*shape, self.model.nu),
            torch.as_tensor(high, dtype=dtype).expand(*shape, self.model.nu),
            shape=(*shape, self.model.nu),
            dtype=dtype,
        )
        self.reward_spec = Unbounded(shape=(*shape, 1), dtype=dtype)
        self.done_spec = Composite(
            done=Categorical(2, shape=(*shape, 1), dtype=torch.bool),
            terminated=Categorical(2, shape=(*shape, 1), dtype=torch.bool),
            truncated=Categorical(2, shape=(*shape, 1), dtype=torch.bool),
            shape=shape,
        )

    def _make_batch(self, threads: int) -> Batch:
        """The ``n_sims`` simulations of the model, stepped natively on ``threads`` threads
        (:class:`armeta_rl.envs.ant_goal_warp.AntGoalWarpEnv` puts them on MuJoCo Warp)."""
        return Batch(self.model, self.n_sims, nthread=threads)

    def _new_observation(self) -> np.ndarray:
        """The observation buffer ``[n_sims, 119]``, of the simulation's array type."""
        return np.empty((self.n_sims, observation_size(self.model)))

    def _as_sim(self, tensor: torch.Tensor) -> np.ndarray:
        """``tensor`` as the simulation's array type: float64 NumPy on the CPU (a view when it is
        a float64 CPU tensor already)."""
        return tensor.detach().to("cpu", torch.float64).numpy()

    def _as_torch(self, array: np.ndarray) -> torch.Tensor:
        """An array of the simulation's type as a torch tensor (a view)."""
        return torch.from_numpy(array)

    def _set_goal(self, goal: torch.Tensor) -> None:
        """Keep the goals ``[*batch, 2]`` (float64 on the CPU, where the reset draws are made) and
        their copy ``[n_sims, 2]`` in the simulation's array type, which the reward reads."""
        self._goal = goal
        self._sim_goal = self._as_sim(goal.reshape(self.n_sims, 2))

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self._generator.manual_seed(int(seed))

    def _observe(self) -> np.ndarray:
        """Fill the observation buffer ``[n_sims, 119]`` and the clipped forces from the batch
        (NumPy or torch: the same slices and methods)."""
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

    def _output(self, extra: dict[str, torch.Tensor]) -> TensorDict:
        shape, dtype = self.batch_size, torch.get_default_dtype()
        # a copy: the buffer is overwritten by the next step
        observation = self._as_torch(self._obs).to(dtype, copy=True).reshape(*shape, -1)
        return TensorDict(
            {"observation": observation, TASK_KEY: self._goal.to(dtype), **extra},
            batch_size=shape,
            device=self.device,
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        shape = self.batch_size
        reset = None if tensordict is None else tensordict.get("_reset", None)
        mask = (
            torch.ones(*shape, 1, dtype=torch.bool)
            if reset is None
            else reset.reshape(*shape, 1).cpu()
        )
        goal = read_identifiers(tensordict, GOAL_NAMES, -math.inf, math.inf, shape)
        if goal is not None:
            goal = goal.to("cpu", torch.float64)
            self._set_goal(torch.where(mask, goal, self._goal))
        steps = self._steps
        self._steps = torch.where(mask.to(steps.device), torch.zeros_like(steps), steps)
        ids = np.flatnonzero(mask.reshape(-1).numpy())
        if ids.size:
            self._reset_sims(ids)
        self._observe()
        false = torch.zeros(*shape, 1, dtype=torch.bool)
        return self._output(
            {"done": false, "terminated": false.clone(), "truncated": false.clone()}
        )

    def _reset_sims(self, ids: np.ndarray) -> None:
        """gymnasium's Ant reset: qpos0 + U(±s), s·N(0, 1) velocities, then a forward pass."""
        scale, n = self.reset_noise_scale, ids.size
        gen, nq, nv = self._generator, self.model.nq, self.model.nv
        qpos_noise = scale * (2 * torch.rand(n, nq, generator=gen, dtype=torch.float64) - 1)
        qvel_noise = scale * torch.randn(n, nv, generator=gen, dtype=torch.float64)
        ids = None if n == self.n_sims else ids.astype(np.int32)
        self.sim.reset(ids, stage=_NONE)
        rows = slice(None) if ids is None else ids
        self._qpos[rows] = self._as_sim(torch.from_numpy(self.model.qpos0) + qpos_noise)
        self._qvel[rows] = self._as_sim(qvel_noise)
        self.sim.forward(ids, stage=_ACC)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = self.batch_size
        action = self._as_sim(tensordict.get("action").reshape(self.n_sims, self.model.nu))
        self._ctrl[:] = action
        self.sim.step(nstep=self.frame_skip, stage=_ACC)
        self._observe()
        xy = self._xpos[:, self._torso, :2]
        reward = goal_reward(xy, self._sim_goal, action, self._forces, self.ctrl_cost_weight,
                             self.contact_cost_weight, self.survive_reward)
        state = self._obs[:, : self.model.nq + self.model.nv]
        going_on = healthy(state, self._qpos[:, 2], self.healthy_z_range)
        terminated = self._as_torch(~going_on).reshape(*shape, 1).to(self.device)
        self._steps = self._steps + 1
        truncated = self._steps >= self.max_steps
        reward = self._as_torch(reward).to(torch.get_default_dtype())
        return self._output(
            {
                "reward": reward.reshape(*shape, 1),
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            }
        )
