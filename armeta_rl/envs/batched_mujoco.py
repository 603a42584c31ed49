"""What every batched MuJoCo task env shares (Ant-Pos, Ant-Dir, HalfCheetah-Vel/Dir, Walker2d-Vel):
one :class:`mujoco.batch.Batch` stepping all simulations of a ``[tasks, episodes]`` batch, and
the task protocol on top of it.

Throughput: all ``tasks × episodes`` simulations of one MuJoCo model live in one
:class:`mujoco.batch.Batch`, which steps them natively: ``frame_skip`` physics steps, then the
forward stages the observation needs at the new state (:attr:`BatchedMujocoEnv.stage`), in one
call with no Python per simulation, on ``threads`` native threads. The dynamics (qpos, qvel) are
those of ``mj_step`` exactly; the stages computed after the step change nothing but the fields the
observation reads. Training can split the tasks over worker processes (TorchRL ``ParallelEnv``),
each owning a slice of tasks with its own batch, through
:class:`armeta_rl.collectors.parallel_episodes.TaskSplitEpisodeCollector`
(``benchmark.collector.workers``).

Task identifiers are passed as ``"params"`` (:data:`~armeta_rl.tasks.TASK_KEY`, ``[*batch, d]``,
in the order of :attr:`~BatchedMujocoEnv.identifier_names`) in the reset TensorDict and kept in
the env's state across automatic (partial) resets; a reset without ``"params"`` keeps the current
ones, and identifiers never set are drawn by the env (``_default_identifiers``) with its seeded
generator. Identifiers under another key (``"goal"``), of another width, not finite or outside
the env's interval raise :class:`~armeta_rl.errors.IdentifierError`. ``"params"`` is emitted with
every observation so that trajectories carry their task; it is also declared in the state spec
so that resets through TorchRL transforms (``TransformedEnv`` forwards only reset and state keys)
still deliver it. Physical identifiers (masses, frictions) are added on top by
:class:`~armeta_rl.envs.mujoco_tasks.PhysicsTaskTransform`, which writes them into the batch's
per-simulation model fields (it finds the batch under ``env.sim`` and the model under
``env.model``).

An episode is truncated after ``max_steps`` steps and terminated where the subclass's health check
fails (a non-finite state, by default).
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
from armeta_rl.rl.policy import GaussianMLP, action_log_density, draw
from armeta_rl.tasks.distributions import TaskEnvMixin
from armeta_rl.tasks.protocol import FORWARD_REWARD, TASK_KEY

KEY = "benchmark.collector"
GYM_ASSETS = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "mujoco", "assets")
STAGE_NONE = mujoco.mjtStage.mjSTAGE_NONE.value
STAGE_POS = mujoco.mjtStage.mjSTAGE_POS.value
STAGE_ACC = mujoco.mjtStage.mjSTAGE_ACC.value


def load_gym_model(xml: str) -> mujoco.MjModel:
    """gymnasium's MuJoCo model ``xml`` (a file of ``gymnasium/envs/mujoco/assets``), compiled.

    A model whose compiler sets ``settotalmass`` (half_cheetah.xml: 14 kg) is compiled without it
    and scaled by ``mj_setTotalmass`` then ``mj_setConst``, as MuJoCo's deprecation warning for
    the attribute prescribes: the same model to the bit (``tests/test_locomotion.py``), without
    the warning MuJoCo 4 prints on every compilation.
    """
    spec = mujoco.MjSpec.from_file(os.path.join(GYM_ASSETS, xml))
    total = spec.compiler.settotalmass
    spec.compiler.settotalmass = -1
    model = spec.compile()
    if total > 0:
        mujoco.mj_setTotalmass(model, total)
        mujoco.mj_setConst(model, mujoco.MjData(model))
    return model


def check_arguments(checks: dict[str, tuple[object, bool, str]]) -> None:
    """One :class:`ConfigError` line, naming ``benchmark.collector.<name>``, for the first failed
    check ``{name: (value, ok, allowed)}`` of an env's constructor arguments."""
    for name, (value, ok, allowed) in checks.items():
        if not ok:
            raise ConfigError(f"{KEY}.{name}", value, allowed)


def common_checks(max_steps: int, frame_skip: int, reset_noise_scale: float,
                  threads: int | None) -> dict[str, tuple[object, bool, str]]:
    """The checks of the arguments every batched MuJoCo env takes."""
    return {
        "max_steps": (max_steps, int(max_steps) >= 1, "must be >= 1"),
        "frame_skip": (frame_skip, int(frame_skip) >= 1, "must be >= 1"),
        "reset_noise_scale": (reset_noise_scale, reset_noise_scale >= 0, "must be >= 0"),
        "threads": (threads, threads is None or int(threads) >= 1,
                    "must be null (one per core) or an integer >= 1"),
    }


class BatchedMujocoEnv(TaskEnvMixin, EnvBase):
    """Base class of the batched MuJoCo task envs (see the module docstring).

    A subclass names its identifiers (:attr:`identifier_names`, their allowed interval
    :attr:`identifier_low`, :attr:`identifier_high`), the forward stage its observation needs
    (:attr:`stage`), and writes :meth:`observation_size`, :meth:`_observe`, :meth:`_reward` and
    :meth:`_default_identifiers`; :meth:`_healthy` and :meth:`_reset_noise` have defaults.

    Args:
        model: the MuJoCo model every simulation runs (per-simulation fields may differ later,
            through :class:`~armeta_rl.envs.mujoco_tasks.PhysicsTaskTransform`).
        batch_size: ``[tasks, episodes]`` (any batch shape works).
        max_steps: time limit in env steps; reaching it sets ``"truncated"``.
        frame_skip: physics steps per env step.
        reset_noise_scale: scale of the initial-state noise (:meth:`_reset_noise`).
        threads: threads stepping the MuJoCo batch natively (1: the calling thread only;
            ``None``: one per CPU core).
        seed: seed of the generator for reset noise and default identifiers.
        device: torch device of the outputs (the physics runs on the CPU).
        require_identifiers: refuse a full reset without identifiers under ``"params"`` (by
            default it keeps the stored ones;
            :class:`~armeta_rl.tasks.protocol.IdentifierCheck`).
    """

    stage: int = STAGE_ACC
    _has_frame_skip = True  # physics substeps run in ``_step``; no FrameSkipTransform wrapper

    def __init__(
        self,
        model: mujoco.MjModel,
        batch_size: Sequence[int],
        max_steps: int,
        frame_skip: int,
        reset_noise_scale: float,
        threads: int | None,
        seed: int | None,
        device: torch.device | str,
        require_identifiers: bool = False,
    ) -> None:
        super().__init__(device=device, batch_size=torch.Size(batch_size))
        self.require_identifiers = bool(require_identifiers)
        self.max_steps, self.frame_skip = int(max_steps), int(frame_skip)
        self.reset_noise_scale = float(reset_noise_scale)
        self.model = model
        self.dt = float(model.opt.timestep) * self.frame_skip
        self.n_sims = math.prod(self.batch_size)
        threads = (os.cpu_count() or 1) if threads is None else int(threads)
        self.sim = self._make_batch(threads)
        self._qpos, self._qvel, self._ctrl = (self.sim.bind(k) for k in ("qpos", "qvel", "ctrl"))
        self._bind_outputs()
        self._obs = self._new_observation()
        self._make_specs()
        self._generator = torch.Generator()
        self._set_seed(seed)
        self._task = self._default_identifiers()
        self._steps = torch.zeros(*self.batch_size, 1, dtype=torch.long, device=self.sim_device)
        self.sim.reset()

    # -- what a subclass states --------------------------------------------------------------

    def observation_size(self) -> int:
        """Length of the observation vector."""
        raise NotImplementedError

    def _bind_outputs(self) -> None:
        """Bind the MjData output fields the observation and reward read (``self.sim.bind``):
        each bound output is copied out after every batch call, so bind only those."""

    def _observe(self) -> np.ndarray:
        """Fill and return the observation buffer ``self._obs`` ``[n_sims, size]`` from the
        batch's state and bound outputs."""
        raise NotImplementedError

    def _reward(self, action: np.ndarray, qpos_before: np.ndarray,
                task: np.ndarray) -> np.ndarray:
        """The reward ``[n_sims]`` of the step just taken, from the action ``[n_sims, nu]`` as
        given, the positions before the step, the task identifiers ``[n_sims, d]`` (float64) and
        the batch's state and observation after it."""
        raise NotImplementedError

    def _default_identifiers(self) -> torch.Tensor:
        """Identifiers ``[*batch_size, d]`` (float64) of simulations never given any, drawn with
        ``self._generator``."""
        raise NotImplementedError

    def _forward_reward(self, qpos_before: np.ndarray, task: np.ndarray) -> np.ndarray | None:
        """The task's own term of the reward ``[n_sims]`` (the references'
        ``info["reward_forward"]``: HalfCheetah-Vel's −|v − goal_velocity|), reported after
        every step as ``"reward_forward"``; ``None`` (the default) for an env that reports
        none. It reads what :meth:`_reward` reads."""
        return None

    @property
    def reports_forward_reward(self) -> bool:
        """Whether the env's steps carry ``"reward_forward"`` (its class defines
        :meth:`_forward_reward`)."""
        return type(self)._forward_reward is not BatchedMujocoEnv._forward_reward

    def _healthy(self) -> np.ndarray:
        """Boolean ``[n_sims]``: the simulation goes on (else the episode terminates). Default: a
        finite state."""
        xp = self.xp
        return xp.isfinite(self._qpos).all(-1) & xp.isfinite(self._qvel).all(-1)

    def _reset_noise(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The perturbations ``([n, nq], [n, nv])`` (float64) added to the model's initial qpos
        and qvel at reset: U(±s) and s·N(0, 1) with s the reset noise scale (gymnasium's
        HalfCheetah and Ant)."""
        scale, gen = self.reset_noise_scale, self._generator
        qpos = scale * (2 * torch.rand(n, self.model.nq, generator=gen, dtype=torch.float64) - 1)
        qvel = scale * torch.randn(n, self.model.nv, generator=gen, dtype=torch.float64)
        return qpos, qvel

    # -- the machinery -----------------------------------------------------------------------

    # -- the simulation's arrays -------------------------------------------------------------
    # The step below is written once for the arrays the batch binds: float64 NumPy arrays here;
    # float32 torch tensors on the warp device for MuJoCo Warp
    # (armeta_rl.envs.warp_physics.WarpSimulation), which overrides these. What reads the bound
    # arrays (_observe, _reward, _forward_reward, _healthy) uses only operators and methods the
    # two share, and the functions of ``xp``.

    xp = np
    """The array module of the bound arrays (``numpy``; ``torch`` on MuJoCo Warp): the functions
    the task's code calls on them (``xp.abs``, ``xp.where``, ...), which the two spell alike."""

    sim_device = torch.device("cpu")
    """Where the bound arrays live, as a torch device."""

    def _new_observation(self) -> np.ndarray:
        """The observation buffer ``[n_sims, size]``, of the simulation's array type."""
        return np.empty((self.n_sims, self.observation_size()))

    def _as_sim(self, tensor: torch.Tensor) -> np.ndarray:
        """``tensor`` as the simulation's array type: float64 NumPy (a view of a float64 CPU
        tensor)."""
        return tensor.detach().to("cpu", torch.float64).numpy()

    def _as_torch(self, array: np.ndarray) -> torch.Tensor:
        """An array of the simulation's type as a torch tensor on :attr:`sim_device` (a view)."""
        return torch.from_numpy(array)

    def _snapshot(self, array: np.ndarray) -> np.ndarray:
        """A copy of a bound array (its values before the next batch call)."""
        return array.copy()

    def _make_batch(self, threads: int) -> Batch:
        """The ``n_sims`` simulations of the model, stepped natively on ``threads`` threads
        (:class:`armeta_rl.envs.warp_physics.WarpSimulation` puts them on MuJoCo Warp)."""
        return Batch(self.model, self.n_sims, nthread=threads)

    def _make_specs(self) -> None:
        """The TorchRL specs: observation and identifiers, the identifiers as state, the
        actuators' box, reward and done flags, all of batch shape ``batch_size``."""
        shape, dtype = self.batch_size, torch.get_default_dtype()
        width = len(self.identifier_names)
        low, high = self.model.actuator_ctrlrange.T
        self.observation_spec = Composite(
            {"observation": Unbounded(shape=(*shape, self._obs.shape[1]), dtype=dtype),
             TASK_KEY: Unbounded(shape=(*shape, width), dtype=dtype),
             **({FORWARD_REWARD: Unbounded(shape=(*shape, 1), dtype=dtype)}
                if self.reports_forward_reward else {})},
            shape=shape,
        )
        # The identifiers are also a state entry, so that TransformedEnv (which passes only reset
        # and state keys to the base env's reset) forwards them; the env's own copy stays
        # authoritative.
        self.state_spec = Composite({TASK_KEY: Unbounded(shape=(*shape, width), dtype=dtype)},
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

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self._generator.manual_seed(int(seed))

    def _observation(self) -> torch.Tensor:
        """The observation buffer as the env emits it, ``[*batch_size, size]`` in torch's default
        dtype (a copy: the buffer is refilled by the next step)."""
        observation = self._as_torch(self._obs).to(torch.get_default_dtype(), copy=True)
        return observation.reshape(*self.batch_size, -1).to(self.device)

    def _output(self, extra: dict[str, torch.Tensor]) -> TensorDict:
        return TensorDict(
            {"observation": self._observation(),
             TASK_KEY: self._task.to(torch.get_default_dtype()), **extra},
            batch_size=self.batch_size,
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
        task = self.identifier_check.read(tensordict, shape)
        if task is not None:
            task = task.to("cpu", torch.float64)
            self._task = torch.where(mask, task, self._task)
        steps = self._steps
        self._steps = torch.where(mask.to(steps.device), torch.zeros_like(steps), steps)
        ids = np.flatnonzero(mask.reshape(-1).numpy())
        if ids.size:
            self._reset_sims(ids)
        self._observe()
        false = torch.zeros(*shape, 1, dtype=torch.bool)
        forward = ({FORWARD_REWARD: torch.zeros(*shape, 1, dtype=torch.get_default_dtype())}
                   if self.reports_forward_reward else {})
        return self._output(
            {"done": false, "terminated": false.clone(), "truncated": false.clone(), **forward}
        )

    def _reset_sims(self, ids: np.ndarray) -> None:
        """gymnasium's MuJoCo reset: the model's initial qpos and qvel plus :meth:`_reset_noise`,
        then the forward pass up to :attr:`stage`."""
        qpos_noise, qvel_noise = self._reset_noise(ids.size)
        ids = None if ids.size == self.n_sims else ids.astype(np.int32)
        self.sim.reset(ids, stage=STAGE_NONE)
        rows = slice(None) if ids is None else ids
        self._qpos[rows] = self._as_sim(torch.from_numpy(self.model.qpos0) + qpos_noise)
        self._qvel[rows] = self._as_sim(qvel_noise)
        self.sim.forward(ids, stage=self.stage)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._output(self._advance(tensordict.get("action")))

    def _advance(self, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """One env step under ``action`` ``[*batch_size, nu]``: the simulations stepped, and the
        step's reward, done flags and (where the env reports it) forward reward, each
        ``[*batch_size, 1]``; the observation is left in its buffer."""
        shape = self.batch_size
        action = self._as_sim(action.reshape(self.n_sims, self.model.nu))
        qpos_before = self._snapshot(self._qpos)
        self._ctrl[:] = action
        self.sim.step(nstep=self.frame_skip, stage=self.stage)
        self._observe()
        task = self._as_sim(self._task.reshape(self.n_sims, -1))
        reward = self._as_torch(self._reward(action, qpos_before, task))
        forward = self._forward_reward(qpos_before, task)
        terminated = self._as_torch(~self._healthy()).reshape(*shape, 1)
        self._steps.add_(1)  # in place: the env is an nn.Module, whose attribute writes cost more
        truncated = self._steps >= self.max_steps
        dtype = torch.get_default_dtype()
        return {
            "reward": reward.to(dtype).reshape(*shape, 1),
            "done": terminated | truncated,
            "terminated": terminated,
            "truncated": truncated,
            **({} if forward is None else
               {FORWARD_REWARD: self._as_torch(forward).to(dtype).reshape(*shape, 1)}),
        }

    def gaussian_transitions(self, steps: int, net: GaussianMLP,
                             params: TensorDictBase | None = None) -> TensorDict:
        """``env.rollout(steps, GaussianActor(net, params), auto_reset=False,
        break_when_any_done=False)`` from the env's current state (after a reset): the same
        rollout bit for bit (``tests/test_locomotion.py``), without TorchRL's per-step env
        machinery (a TensorDict built, checked and stepped through per step), which costs a
        large share of a small batch's physics.

        Each step the policy draws its action (:func:`~armeta_rl.rl.policy.draw`: the actor's
        draws from torch's RNG) on the observation, :meth:`_advance` steps the simulations, and
        the episodes that ended are reset between steps as TorchRL's automatic partial reset
        resets them (:meth:`_reset` of the done entries, never after the last step). The
        actions' log-densities, elementwise arithmetic, are taken once over the whole rollout
        (:func:`~armeta_rl.rl.policy.action_log_density`), the actor's values per step.

        Returns a TensorDict ``[*batch_size, steps]`` with ``"observation"``, ``"params"``,
        ``"loc"``, ``"scale"``, ``"action"``, ``"action_log_prob"`` and ``"next"``:
        ``"observation"``, ``"params"``, ``"reward"``, ``"done"``, ``"terminated"``,
        ``"truncated"`` and, where the env reports it, ``"reward_forward"``.
        """
        per_task = params is not None
        named = params.flatten_keys(".").to_dict() if per_task else {
            name: value.detach() for name, value in net.named_parameters()}
        batch, n_steps = self.batch_size, int(steps)
        observation = self._observation()
        acted, moved = [], []
        for t in range(n_steps):
            loc, scale, action = draw(net, named, observation, per_task)
            acted.append({"observation": observation, "loc": loc, "scale": scale,
                          "action": action})
            outputs = self._advance(action)
            observation = outputs["observation"] = self._observation()
            moved.append(outputs)
            done = outputs["done"]
            if t < n_steps - 1 and done.any():
                reset = self._reset(TensorDict({"_reset": done}, batch))["observation"]
                observation = torch.where(done.to(self.device), reset, observation)
        dim = len(batch)
        task = self._task.to(torch.get_default_dtype()).unsqueeze(dim)
        task = task.expand(*batch, n_steps, task.shape[-1])
        rollout = TensorDict({key: torch.stack([step[key] for step in acted], dim)
                              for key in acted[0]}, [*batch, n_steps], device=self.device)
        # the scale is the same at every step: its log too, taken once at a step's shape
        log_scale = acted[0]["scale"].log().unsqueeze(dim)
        rollout["action_log_prob"] = action_log_density(rollout["loc"], rollout["scale"],
                                                        rollout["action"], log_scale)
        rollout["next"] = TensorDict({key: torch.stack([step[key] for step in moved], dim)
                                      for key in moved[0]}, [*batch, n_steps],
                                     device=self.device)
        rollout.update({TASK_KEY: task.clone(), ("next", TASK_KEY): task.clone()})
        return rollout
