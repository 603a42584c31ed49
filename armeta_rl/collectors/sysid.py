"""System-identification data: random-policy transitions of one simulated system per task
(paper, appendix "System Identification")."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict
from torch import Tensor

from armeta_rl.compiling import compile_backend
from armeta_rl.devices import CPU
from armeta_rl.envs.identified_env import IdentifiedSystemEnv
from armeta_rl.envs.pendulum import PendulumEnv
from armeta_rl.errors import ConfigError
from armeta_rl.tasks.protocol import TASK_KEY
from armeta_rl.tasks.space import TaskSpace

TARGETS = ("delta", "next")
NORMALIZATIONS = ("none", "scale")


class SysIdCollector:
    """Few-shot transition data for system identification (the ``TaskCollector`` protocol).

    For tasks ``[K]`` with identifiers ``"params"`` (``TASK_KEY``) ``[K, d]`` ((m, l) for the
    pendulum by default, any of (m, l, g) with ``identifiers``; (m1, m2) for the acrobot), one
    batched env ``[K, episodes]`` (made by ``make_env``, as the episode collectors make theirs)
    is reset with those identifiers
    and a uniformly random policy acts for ``n_transitions / episodes`` steps (finished acrobot
    episodes are reset and collection goes on). The steps are
    :meth:`~armeta_rl.envs.identified_env.IdentifiedSystemEnv.transitions`: ``env.rollout``'s
    transitions bit for bit, without TorchRL's per-step TensorDicts, which cost a hundred times
    the physics of these envs. Each task's
    ``n_transitions`` transitions are split at random (torch's global RNG) into ``n_support``
    support and ``n_transitions - n_support`` query points::

        x = (observation, torque)            y = next observation − observation  ("delta")
                                             y = next observation                ("next")

    With ``normalize="scale"`` every observation component of ``x`` and ``y`` is divided by its
    bound in the observation spec (1 for cos/sin, the speed limits for velocities) and the
    torque by its bound, so all inputs lie in [-1, 1]; ``"none"`` keeps physical units. Losses
    are computed on ``y`` as returned.

    The defaults ``target="delta"``, ``normalize="none"`` learned best of the four pairs on both
    envs (docs/notes/history.md).

    ``episodes=20`` (20 episodes of 10 steps per task): a step costs about the same for any
    batch, so collection time grows with the steps per episode (see
    docs/notes/speed-measurements.md). Shorter episodes stay closer to the initial states
    (the velocities they cover: docs/notes/history.md).

    The environment's initial-state seed is drawn from torch's global RNG at every call, so
    ``torch.manual_seed`` fixes the whole collection.

    Args:
        make_env: makes the system's env, an
            :class:`~armeta_rl.envs.identified_env.IdentifiedSystemEnv` (``PendulumEnv``,
            ``AcrobotEnv``, or a class or ``functools.partial`` of a new family), called with
            ``batch_size``, ``seed``, ``device``, ``identifiers`` and ``compile_dynamics``; a
            benchmark gives it as a Hydra node with ``_partial_: true``.
        n_transitions: transitions per task (paper: 200).
        n_support: support transitions per task (paper: 10).
        episodes: episodes per task sharing the ``n_transitions`` (must divide it).
        target: ``"delta"`` or ``"next"``.
        normalize: ``"none"`` or ``"scale"``.
        device: torch device of the environments and the returned data.
        identifiers: the env's task identifiers, in the order of ``"params"`` (default: the
            env's :attr:`~armeta_rl.envs.identified_env.IdentifiedSystemEnv.param_names`, e.g.
            ``[m, l]``; the pendulum also takes ``g``). A benchmark sets it to
            ``${benchmark.space.names}``.
        compile: the envs' physics step through ``torch.compile`` (``false``: eager; ``true``:
            inductor; or a backend name, :func:`~armeta_rl.compiling.compile_backend`). It pays
            where the physics is long and sequential (the acrobot's Runge–Kutta step in the
            paper protocol's 200-step episodes), on long runs: the first collection of each
            batch shape waits for the compiler (docs/speed-options.md).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors import SysIdCollector
        >>> from armeta_rl.envs import PendulumEnv
        >>> _ = torch.manual_seed(0)
        >>> collector = SysIdCollector(PendulumEnv, n_transitions=40, n_support=10, episodes=4)
        >>> tasks = TensorDict({"params": torch.tensor([[1.0, 1.0], [0.5, 1.5]])}, [2])  # (m, l)
        >>> data = collector.collect(tasks)  # x = (cos θ, sin θ, θ̇, torque), y = Δ observation
        >>> x = torch.cat([data["support", "x"], data["query", "x"]], 1)  # 40 transitions a task
        >>> y = torch.cat([data["support", "y"], data["query", "y"]], 1)
        >>> # Δθ̇ = 3g/(2l)·dt·sin θ + 3/(m l²)·dt·torque (dt = 0.05, g = 10): the data tell (m, l)
        >>> torch.linalg.lstsq(x[..., [1, 3]], y[..., 2:]).solution.squeeze(-1).round(decimals=4)
        tensor([[0.7500, 0.1500],
                [0.5000, 0.1333]])
    """

    def __init__(self, make_env: Callable[..., IdentifiedSystemEnv] = PendulumEnv,
                 n_transitions: int = 200, n_support: int = 10, episodes: int = 20,
                 target: str = "delta", normalize: str = "none", device: torch.device = CPU,
                 identifiers: Sequence[str] | None = None,
                 compile: bool | str | None = False) -> None:
        if not isinstance(n_transitions, int) or n_transitions < 2:
            raise ConfigError("benchmark.collector.n_transitions", n_transitions,
                              "an integer >= 2")
        if not isinstance(n_support, int) or not 1 <= n_support < n_transitions:
            raise ConfigError("benchmark.collector.n_support", n_support,
                              f"an integer in [1, n_transitions={n_transitions})")
        if not isinstance(episodes, int) or episodes < 1 or n_transitions % episodes:
            raise ConfigError("benchmark.collector.episodes", episodes,
                              f"a positive integer dividing n_transitions={n_transitions}")
        if target not in TARGETS:
            raise ConfigError("benchmark.collector.target", target,
                              f"allowed: {', '.join(TARGETS)}")
        if normalize not in NORMALIZATIONS:
            raise ConfigError("benchmark.collector.normalize", normalize,
                              f"allowed: {', '.join(NORMALIZATIONS)}")
        probe = make_env(batch_size=(1, 1), seed=0, device=CPU)  # the system's constants
        if not isinstance(probe, IdentifiedSystemEnv):
            raise ConfigError("benchmark.collector.make_env", type(probe).__name__,
                              "must make an IdentifiedSystemEnv (armeta_rl.envs.identified_env)")
        self.make_env, self.env_cls = make_env, type(probe)
        known = tuple(self.env_cls.identifier_defaults)
        if identifiers is not None and (
                not identifiers or len(set(identifiers)) < len(identifiers)
                or not set(identifiers) <= set(known)):
            raise ConfigError("benchmark.collector.identifiers", list(identifiers),
                              f"distinct names among {', '.join(known)} "
                              f"({self.env_cls.__name__})")
        self.identifiers = tuple(self.env_cls.param_names if identifiers is None else identifiers)
        self.n_transitions, self.n_support, self.episodes = n_transitions, n_support, episodes
        self.target, self.normalize, self.device = target, normalize, device
        self.backend = compile_backend("benchmark.collector.compile", compile)
        self._envs: dict[int, IdentifiedSystemEnv] = {}
        x_scale, y_scale = self._scales()
        self.x_scale, self.y_scale = x_scale.to(self.device), y_scale.to(self.device)

    @property
    def in_features(self) -> int:
        """Size of ``x``: observation and torque."""
        return self.env_cls.observation_dim + 1

    @property
    def out_features(self) -> int:
        """Size of ``y``: one value per observation component."""
        return self.env_cls.observation_dim

    def _scales(self) -> tuple[Tensor, Tensor]:
        if self.normalize == "none":
            return torch.ones(self.in_features), torch.ones(self.out_features)
        observation = torch.tensor(self.env_cls.observation_high)
        torque = torch.tensor([self.env_cls.max_torque])
        return torch.cat([observation, torque]), observation

    def _env(self, n_tasks: int) -> IdentifiedSystemEnv:
        if n_tasks not in self._envs:
            self._envs[n_tasks] = self.make_env(batch_size=(n_tasks, self.episodes), seed=0,
                                                device=self.device,
                                                identifiers=self.identifiers,
                                                compile_dynamics=self.backend)
        return self._envs[n_tasks]

    def check_space(self, space: TaskSpace) -> None:
        """Refuse a task box the env cannot take: names other than its identifiers, or a lower
        corner that is not positive (masses, lengths and gravity are > 0)."""
        if space.names != self.identifiers:
            raise ConfigError("benchmark.space.names", list(space.names),
                              f"{self.env_cls.__name__} takes the identifiers "
                              f"{list(self.identifiers)} (benchmark.collector.identifiers)")
        if not all(low > 0 for low in space.low):
            raise ConfigError("benchmark.space.low", list(space.low),
                              f"{self.env_cls.__name__}'s identifiers must be > 0")

    @torch.inference_mode()
    def rollout(self, params: Tensor) -> TensorDict:
        """Random-policy rollout ``[K, episodes, steps]`` of the systems ``params`` ``[K, d]``.

        The transitions are data that nothing differentiates, so the env runs in
        ``torch.inference_mode``: its many small tensor ops skip autograd's bookkeeping. The
        returned tensors are inference tensors (read them, or copy them before an in-place
        change); :meth:`collect` builds ordinary tensors from them.
        """
        n_tasks = params.shape[0]
        env = self._env(n_tasks)
        env.set_seed(int(torch.randint(0, 2**62, ())))
        batch = (n_tasks, self.episodes)
        params = params.to(self.device)[:, None].expand(*batch, -1)
        env.reset(TensorDict({TASK_KEY: params}, batch_size=batch, device=self.device))
        return env.transitions(self.n_transitions // self.episodes)

    def collect(self, tasks: TensorDict, policy_params: TensorDict | None = None) -> TensorDict:
        """Support and query transitions for every task: TensorDict ``[K]`` with
        ``{"support", "query"}`` × ``{"x", "y"}``, tensors ``[K, points, features]``."""
        params = tasks[TASK_KEY]
        n_tasks, n_points = params.shape[0], self.n_transitions
        data = self.rollout(params)
        observation = data["observation"].reshape(n_tasks, n_points, -1)
        next_observation = data["next", "observation"].reshape(n_tasks, n_points, -1)
        torque = self.env_cls.torque(data["action"]).reshape(n_tasks, n_points, 1)
        if self.target == "delta":
            next_observation = next_observation - observation
        # One [K, points, x | y] tensor: one scaling, one shuffle, then the split.
        points = torch.cat([observation, torque.to(observation.dtype), next_observation], -1)
        if self.normalize != "none":
            points = points / torch.cat([self.x_scale, self.y_scale])
        order = torch.rand(n_tasks, n_points).argsort(-1).to(self.device)
        points = points.gather(1, order.unsqueeze(-1).expand_as(points))
        points = points.to(torch.get_default_dtype())
        x = points[..., : self.in_features].contiguous()
        y = points[..., self.in_features :].contiguous()
        support, query = slice(None, self.n_support), slice(self.n_support, None)
        split = {
            "support": {"x": x[:, support], "y": y[:, support]},
            "query": {"x": x[:, query], "y": y[:, query]},
        }
        return TensorDict(split, batch_size=[n_tasks], device=self.device)
