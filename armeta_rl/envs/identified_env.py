"""A batched TorchRL environment whose physical identifiers are set through the reset TensorDict.

System identification (paper, appendix "System Identification") needs one dynamical system per
task: the task identifiers (pendulum mass and length, acrobot link masses) are physical constants
of the simulator. Subclasses write the batched physics; this base class owns what they share:

* batch size ``[tasks, episodes]``; every tensor entry carries it as leading dimensions;
* ``"params"`` (:data:`~armeta_rl.tasks.TASK_KEY`) ``[*batch, d]`` (identifiers in the order of
  :attr:`param_names`, chosen with ``identifiers=`` among :attr:`identifier_defaults`) is read
  from the reset TensorDict and kept: the env stores the last identifiers it was given, so an
  automatic (partial) reset inside ``env.rollout`` or ``torchrl.collectors.Collector`` restores
  them. ``"params"`` is declared in the state spec as well as the observation spec, so
  ``TransformedEnv`` (which hands the base env only reset and state keys) and batched envs forward
  it. Steps simulate the stored identifiers and report them under ``"params"`` like an
  observation. A reset TensorDict without ``"params"`` keeps the stored ones (with
  ``require_identifiers=True`` a full reset without them is refused); identifiers under another
  key, an empty reset TensorDict, identifiers of another width, or not positive and finite raise
  :class:`~armeta_rl.errors.IdentifierError` (the reset contract of
  :class:`armeta_rl.tasks.protocol.IdentifierCheck`), bare, behind transforms and in batched envs;
* the exact simulator state is kept by the env (the observation is a function of it) and reported
  as the observation ``"state"`` ``[*batch, state_dim]``; a step reads only ``"action"``, so
  transforms may drop or cast ``"state"``. ``env.reset(td, from_state=True)`` starts from
  ``td["state"]`` instead of a random one. The env does not declare TorchRL's ``set_state``:
  TorchRL counts every state-spec entry, the identifiers included, as a state to set, and a
  batched env would warn (and from TorchRL 0.15 drop the identifiers) at every reset carrying
  them;
* a ``torch.Generator`` owned by the env draws the random initial states (``set_seed``);
* one step's physics is a pure function of the states and the actions (:meth:`_transition`),
  whose equations of motion (:meth:`_dynamics`) may run through ``torch.compile``
  (``compile_dynamics``; TorchRL's own ``compile`` compiles its per-step machinery instead);
  ``_step`` wraps it for TorchRL, and :meth:`transitions` steps it without TorchRL's per-step
  machinery: the rollout of ``env.rollout``, transition for transition and bit for bit
  (``tests/test_sysid_envs.py``), at a fraction of its cost.

The physics runs on flat ``[tasks * episodes, ...]`` views with few, fused tensor ops: a step
costs one small op per arithmetic stage, so its time is set by the op count, not the batch size.
Inside a step the envs keep the state feature-major, ``[state_dim, n_envs]``, so that every op
reads contiguous rows: an op on a column of ``[n_envs, state_dim]`` is strided, and a strided
``sin`` costs about ten times a contiguous one here.
Identifier-dependent constants are computed once per reset (:meth:`_physical_constants`), not per
step.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from armeta_rl.compiling import compile_backend, maybe_compile
from armeta_rl.errors import ConfigError
from armeta_rl.tasks.distributions import TaskEnvMixin
from armeta_rl.tasks.protocol import TASK_KEY


class UniformBounded(Bounded):
    """A ``Bounded`` spec with one range for every entry whose samples are
    ``Tensor.uniform_(low, high)``: the draws the envs' random actions have always taken (torch's
    global RNG), now through TorchRL's own ``rand_action``."""

    def rand(self, shape: torch.Size | None = None) -> Tensor:
        low, high = (float(bound.reshape(-1)[0]) for bound in self.space)
        out = torch.empty((*(shape or ()), *self.shape), dtype=self.dtype, device=self.device)
        return out.uniform_(low, high)


class IdentifiedSystemEnv(TaskEnvMixin, EnvBase):
    """Base class of the batched system-identification environments.

    Args:
        batch_size: ``(tasks, episodes)`` (any shape works; the collectors use two dimensions).
        seed: seed of the env's generator; ``None`` draws one from torch's global RNG.
        device: torch device of every tensor.
        dtype: floating dtype of the state, observation and reward (float64 to compare with
            gymnasium, which integrates in float64).
        identifiers: the names of the task identifiers, in the order of ``"params"``'s last
            dimension, among :attr:`identifier_defaults` (default :attr:`param_names`); the
            others stay at their defaults.
        compile_dynamics: step the equations of motion (:meth:`_dynamics`) through
            ``torch.compile`` (``None`` or ``False``: eagerly; ``True``: inductor; or a backend
            name, :func:`~armeta_rl.compiling.compile_backend`), in ``env.rollout`` and
            :meth:`transitions` alike. The compiled step rounds differently from the eager one;
            the env is then no longer picklable.
        require_identifiers: refuse a full reset whose TensorDict has no ``"params"`` (by
            default it keeps the stored identifiers, at first :attr:`identifier_defaults`).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import IdentifiedSystemEnv, PendulumEnv
        >>> from armeta_rl.tasks import TASK_KEY
        >>> issubclass(PendulumEnv, IdentifiedSystemEnv), PendulumEnv.identifier_defaults
        (True, {'m': 1.0, 'l': 1.0, 'g': 10.0})
        >>> env = PendulumEnv(batch_size=(2, 1), seed=0, identifiers=["g"])  # m = l = 1 stay
        >>> start = env.reset(TensorDict({TASK_KEY: torch.tensor([[[10.0]], [[5.0]]])}, [2, 1]))
        >>> idle = lambda td: td.set("action", torch.zeros(2, 1, 1))  # no torque
        >>> step = env.rollout(1, idle, tensordict=start, auto_reset=False)
        >>> _, sin, speed = start["observation"].unbind(-1)  # (cos θ, sin θ, θ̇)
        >>> ((step["next", "observation"][..., 0, 2] - speed) / sin).flatten()  # 3g/(2l)·dt
        tensor([0.7500, 0.3750])
    """

    param_names: tuple[str, ...] = ()
    identifier_defaults: dict[str, float] = {}
    identifier_low, identifier_open_low = 0.0, True  # positive and finite
    reset_reads = ("state",)  # a start state, with from_state=True
    state_dim: int = 0
    observation_dim: int = 0
    observation_high: tuple[float, ...] = ()
    max_torque: float = 1.0

    def __init__(self, batch_size: Sequence[int] = (1, 1), seed: int | None = None,
                 device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                 identifiers: Sequence[str] | None = None,
                 compile_dynamics: bool | str | None = None,
                 require_identifiers: bool = False) -> None:
        batch_size = torch.Size(batch_size)
        if any(n < 1 for n in batch_size):
            raise ConfigError("env.batch_size", list(batch_size), "every dimension must be >= 1")
        if identifiers is not None:
            names = tuple(str(name) for name in identifiers)
            known = tuple(self.identifier_defaults)
            if not names or len(set(names)) < len(names) or not set(names) <= set(known):
                raise ConfigError("env.identifiers", list(identifiers),
                                  f"distinct names among {', '.join(known)}")
            self.param_names = names
        super().__init__(device=device, batch_size=batch_size)
        self.require_identifiers = bool(require_identifiers)
        self.dtype = dtype
        self.n_envs = batch_size.numel()
        self._physics = maybe_compile(self._dynamics,
                                      compile_backend("env.compile_dynamics", compile_dynamics))
        # Scalars of the physics are 0-dim tensors: an op with a Python number costs about twice
        # one with a tensor.
        self.pi = torch.tensor(math.pi, dtype=dtype, device=self.device)
        self.two_pi = 2 * self.pi
        self._precompute()
        default = [self.identifier_defaults[name] for name in self.param_names]
        default = torch.tensor(default, dtype=dtype, device=self.device)
        self._identify(default.expand(*batch_size, len(self.param_names)).clone())
        self._state = self._state_rows(torch.zeros(*batch_size, self.state_dim, dtype=dtype,
                                                  device=self.device))
        self._make_specs()
        if seed is None:
            seed = int(torch.randint(0, 2**62, ()))
        self.set_seed(seed)

    @property
    def identifier_names(self) -> tuple[str, ...]:
        """The identifiers this env was built with (:attr:`param_names`)."""
        return self.param_names

    def _make_specs(self) -> None:
        batch, kwargs = self.batch_size, {"dtype": self.dtype, "device": self.device}
        params = Unbounded(shape=(*batch, len(self.param_names)), **kwargs)
        self.observation_spec = Composite(
            {"observation": self._observation_bounds(),
             "state": Unbounded(shape=(*batch, self.state_dim), **kwargs),
             TASK_KEY: params},
            shape=batch,
        )
        self.state_spec = Composite({TASK_KEY: params.clone()}, shape=batch)
        self.action_spec = self._make_action_spec()
        self._action_rank = len(self.action_spec.shape)  # an action's dims, batch included
        self.reward_spec = Unbounded(shape=(*batch, 1), **kwargs)
        done = Categorical(n=2, shape=(*batch, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(done=done, terminated=done.clone(), shape=batch)

    def _observation_bounds(self) -> Bounded:
        high = torch.tensor(self.observation_high, dtype=self.dtype, device=self.device)
        high = high.expand(*self.batch_size, self.observation_dim)
        return Bounded(low=-high, high=high, dtype=self.dtype, device=self.device)

    @staticmethod
    def torque(action: Tensor) -> Tensor:
        """The torque ``[..., 1]`` an action applies."""
        raise NotImplementedError

    def _precompute(self) -> None:
        """Build the constant tensors (in the env's dtype and device) the physics reuses."""

    def _physical_constants(self, params: Tensor) -> Tensor:
        """Identifier-dependent constants ``[n_envs, c]`` of the equations of motion, from the
        flat identifiers ``[n_envs, d]``."""
        raise NotImplementedError

    def _wrap_angles_(self, angles: Tensor) -> Tensor:
        """Wrap ``angles`` into ``[-π, π)`` in place (gymnasium's ``angle_normalize`` and
        ``wrap``, equal up to the value at ±π)."""
        return angles.add_(self.pi).remainder_(self.two_pi).sub_(self.pi)

    def _identify(self, params: Tensor) -> None:
        """Store the identifiers ``[*batch, d]`` and the constants the physics derives from
        them (:attr:`constants`: one flat ``[n_envs]`` tensor per constant)."""
        self.task_params = params
        flat = params.reshape(self.n_envs, -1)
        self.constants = self._physical_constants(flat).T.contiguous().unbind(0)

    def _make_action_spec(self):
        raise NotImplementedError

    def _initial_state(self) -> Tensor:
        """Random initial states ``[*batch, state_dim]`` drawn with the env's generator."""
        raise NotImplementedError

    def _state_rows(self, state: Tensor) -> Tensor:
        """A feature-major copy ``[state_dim, n_envs]`` of states ``[*batch, state_dim]``."""
        return state.reshape(self.n_envs, self.state_dim).T.contiguous()

    def _observe_rows(self, state: Tensor) -> Tensor:
        """Feature-major observations ``[observation_dim, n_envs]`` of feature-major states
        ``[state_dim, n_envs]``."""
        raise NotImplementedError

    def _set_seed(self, seed: int | None) -> None:
        self.rng = torch.Generator(device=self.device)
        self.rng.manual_seed(seed)

    def _uniform(self, low: float, high: float) -> Tensor:
        shape = (*self.batch_size, self.state_dim)
        unit = torch.rand(shape, generator=self.rng, dtype=self.dtype, device=self.device)
        return low + (high - low) * unit

    def _reset(self, tensordict: TensorDictBase | None, from_state: bool = False,
               **kwargs) -> TensorDictBase:
        """New episodes where ``"_reset"`` is set (all if absent), with the stored identifiers
        updated from ``tensordict["params"]`` when given (checked by
        :attr:`identifier_check`: positive and finite), from
        ``tensordict["state"]`` with ``from_state=True``, else from random states."""
        params = self.identifier_check.read(tensordict, self.batch_size)
        tensordict = tensordict if tensordict is not None else TensorDict({}, self.batch_size)
        reset = tensordict.get("_reset", None)
        if params is not None:
            params = params.to(self.task_params)
            self._identify(params.clone() if reset is None else torch.where(
                reset, params, self.task_params))
        state = tensordict.get("state", None)
        if not from_state or state is None:
            state = self._initial_state()
        rows = self._reset_rows(state, reset, self._state)
        self._state = rows
        observation = self._observe_rows(rows).T
        done = torch.zeros((self.n_envs, 1), dtype=torch.bool, device=self.device)
        return self._output(rows.T, observation, None, done)

    def _reset_rows(self, state: Tensor, reset: Tensor | None, current: Tensor) -> Tensor:
        """Feature-major states ``[state_dim, n_envs]``: ``state`` ``[*batch, state_dim]`` where
        ``reset`` ``[*batch, 1]`` is set (everywhere if ``None``), ``current`` elsewhere."""
        rows = self._state_rows(state.to(self.dtype))
        if reset is None:
            return rows
        return torch.where(reset.reshape(1, self.n_envs), rows, current)

    def _forcing(self, action: Tensor) -> Tensor:
        """What actions put into the equations of motion, one number per env: ``[*steps,
        n_envs]`` for actions ``[*steps, *action_shape]`` (the action spec's shape after any
        leading step dimensions), under the env's identifiers. An elementwise function of each
        action, so :meth:`transitions` takes the forcing of all its random actions in one call
        instead of one per step (the same values)."""
        raise NotImplementedError

    def _per_env(self, action: Tensor) -> Tensor:
        """Actions ``[*steps, *action_shape]`` as ``[*steps, n_envs]``: one number per env."""
        steps = action.shape[: action.dim() - self._action_rank]
        return action.reshape(*steps, self.n_envs)

    def _dynamics(self, state: Tensor, forcing: Tensor) -> Tensor:
        """The states after one step ``[state_dim, n_envs]`` from feature-major states and the
        step's forcing ``[n_envs]`` (:meth:`_forcing` of its actions), under the env's
        identifiers: the equations of motion."""
        raise NotImplementedError

    def _reward(self, state: Tensor, action: Tensor, new_state: Tensor) -> Tensor:
        """The rewards ``[n]`` of steps from feature-major states ``[state_dim, n]`` with actions
        ``[n, ...]`` to ``new_state``; elementwise, so any number ``n`` of steps at once."""
        raise NotImplementedError

    def _terminated(self, new_state: Tensor) -> Tensor | None:
        """Whether each step ending in feature-major states ``[state_dim, n]`` terminates its
        episode ``[n]`` (bool); ``None``: never (the default)."""
        return None

    def _random_actions(self, steps: int) -> Tensor:
        """``steps`` uniform random actions ``[steps, *batch, ...]`` in one draw: the values of
        ``steps`` calls of :meth:`_random_action` (torch's CPU generator draws elementwise, in
        order)."""
        raise NotImplementedError

    def _transition(self, state: Tensor, action: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """One step of the physics, a pure function of feature-major states
        ``[state_dim, n_envs]`` and actions (the action spec's shape) under the env's
        identifiers: the new states, their feature-major observations
        ``[observation_dim, n_envs]``, the rewards ``[n_envs]`` and the terminations
        ``[n_envs, 1]`` (bool)."""
        new_state = self._physics(state, self._forcing(action))
        terminated = self._terminated(new_state)
        if terminated is None:
            terminated = torch.zeros((self.n_envs, 1), dtype=torch.bool, device=self.device)
        reward = self._reward(state, action.reshape(self.n_envs, -1), new_state)
        return new_state, self._observe_rows(new_state), reward, terminated

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        state, observation, reward, terminated = self._transition(self._state,
                                                                  tensordict["action"])
        self._state = state
        return self._output(state.T, observation.T, reward, terminated)

    def transitions(self, steps: int,
                    policy: Callable[[TensorDictBase], TensorDictBase] | None = None
                    ) -> TensorDict:
        """``env.rollout(steps, policy, auto_reset=False, break_when_any_done=False)`` from the
        env's current state (after a reset), without TorchRL's per-step TensorDicts and checks,
        which cost a hundred times the physics of these small envs.

        Equal to ``env.rollout`` transition for transition, bit for bit
        (``tests/test_sysid_envs.py``): the same actions (``policy`` reads ``"observation"`` from
        a TensorDict and writes ``"action"``, as a TorchRL policy module does; ``None``: the
        uniformly random actions of :meth:`rand_action`, the same draws from torch's global RNG,
        taken at once), terminated
        entries reset between steps as TorchRL's automatic partial reset resets them (new initial
        states from the env's generator; never after the last step), and the same maths: only the
        equations of motion (:meth:`_dynamics`) run step by step; the random actions' forcing
        (:meth:`_forcing`), and the observations, rewards and terminations, elementwise functions
        of the actions and the states, are computed for all steps at once.

        Returns a TensorDict ``[*batch, steps]`` with ``"observation"``, ``"state"``,
        ``"action"``, ``"params"`` and ``"next"``: ``"observation"``, ``"state"``, ``"reward"``,
        ``"done"``, ``"terminated"``, ``"params"``, as ``env.rollout`` writes them.
        """
        batch, n_steps = self.batch_size, int(steps)
        random = self._random_actions(n_steps) if policy is None else None
        random_forcing = None if random is None else self._forcing(random)
        state = self._state
        starts, ends, actions = [], [], []
        for t in range(n_steps):
            if random is None:
                observation = self._observe_rows(state).T.reshape(*batch, self.observation_dim)
                action = policy(TensorDict({"observation": observation}, batch,
                                           device=self.device)).get("action")
                actions.append(action)
                forcing = self._forcing(action)
            else:
                forcing = random_forcing[t]
            new_state = self._physics(state, forcing)
            starts.append(state)
            ends.append(new_state)
            state = new_state
            if t < n_steps - 1:
                terminated = self._terminated(new_state)
                if terminated is not None and bool(terminated.any()):
                    state = self._reset_rows(self._initial_state(), terminated, new_state)
        self._state = new_state
        steps_shape, flat = (*batch, n_steps), self.n_envs * n_steps
        # [T, state_dim, n_envs] -> [state_dim, T * n_envs]: every step's states side by side
        start = torch.stack(starts, 1).reshape(self.state_dim, flat)
        end = torch.stack(ends, 1).reshape(self.state_dim, flat)
        action = (torch.stack(actions) if random is None else random).reshape(flat, -1)
        terminated = self._terminated(end)
        if terminated is None:
            terminated = torch.zeros(flat, dtype=torch.bool, device=self.device)

        def per_entry(values: Tensor) -> Tensor:  # [width, T * n_envs] -> [*batch, T, width]
            width = values.shape[0]
            return values.reshape(width, n_steps, self.n_envs).permute(2, 1, 0).reshape(
                *steps_shape, width)

        params = self.task_params.unsqueeze(-2).expand(*steps_shape, len(self.param_names))
        done = per_entry(terminated[None])
        action_shape = self.action_spec.shape[len(batch):]
        rollout = {
            "observation": per_entry(self._observe_rows(start)),
            "state": per_entry(start),
            "action": per_entry(action.T).reshape(*steps_shape, *action_shape),
            TASK_KEY: params.clone(),
            "next": {
                "observation": per_entry(self._observe_rows(end)),
                "state": per_entry(end),
                "reward": per_entry(self._reward(start, action, end)[None]),
                "done": done,
                "terminated": done.clone(),
                TASK_KEY: params.clone(),
            },
        }
        return TensorDict(rollout, batch_size=steps_shape, device=self.device)

    def _output(self, state: Tensor, observation: Tensor, reward: Tensor | None,
                terminated: Tensor) -> TensorDictBase:
        """The TensorDict of a reset (``reward=None``) or a step, from flat ``[n_envs, ...]``
        tensors; ``"params"`` are the env's identifiers (the ones the physics used)."""
        batch = self.batch_size
        out = {
            "state": state.reshape(*batch, self.state_dim),
            "observation": observation.reshape(*batch, self.observation_dim),
            TASK_KEY: self.task_params.clone(),
            "done": terminated.reshape(*batch, 1),
            "terminated": terminated.reshape(*batch, 1).clone(),
        }
        if reward is not None:
            out["reward"] = reward.reshape(*batch, 1)
        # Every shape is built here, so the per-entry validation of ``TensorDict(...)`` is
        # skipped, as torchrl's own ``GymLikeEnv._step`` does.
        return TensorDict._new_unsafe(out, batch_size=batch, device=self.device)
