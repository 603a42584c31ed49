"""Episode collector for meta-RL: every task × episode rolls out in one batched env call.

``collect(tasks, policy_params, policy)`` runs ``episodes`` episodes per task in a task-conditioned
env (point navigation, Ant goal, any env taking its identifiers under
:data:`~armeta_rl.tasks.TASK_KEY`) of batch size ``[K, episodes]`` with
``env.rollout`` and a :class:`~armeta_rl.rl.policy.GaussianActor` (the TorchRL
``ProbabilisticActor`` of :func:`~armeta_rl.rl.policy.make_actor`, written out) that acts with
task ``k``'s parameters on row ``k``. Each batch entry runs exactly one episode: the rollout lasts
``max_steps`` steps, and the steps after an entry's first ``done`` (where TorchRL has
automatically reset it) are masked out.
An env whose class offers ``gaussian_transitions(steps, net, params)`` (point navigation, the
batched MuJoCo envs and their physics families) is stepped with it instead: ``env.rollout``'s
rollout bit for bit, without TorchRL's per-step env machinery (the point robot's on CUDA replayed
as one CUDA graph). The same env behind other transforms or in a batched env is stepped by
``env.rollout``, transforms and all.

Devices: the policy acts on the env's device (a torch-native env runs wherever it was built; a
MuJoCo env on the CPU), and the trajectories are returned on the collector's ``device``, where the
leader computes. When the two differ, the rollout acts with a copy of the policy on the env's
device.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from functools import partial

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv

from armeta_rl.devices import CPU
from armeta_rl.envs.point_navigation import (
    TRUNCATED_KEY,
    PointNavigationEnv,
    Region,
    blind_return,
    check_regions,
    reference_return,
)
from armeta_rl.errors import ConfigError, IdentifierError
from armeta_rl.rl.policy import GaussianActor, GaussianMLP
from armeta_rl.tasks.protocol import FORWARD_REWARD, TASK_KEY
from armeta_rl.tasks.space import TaskSpace


def valid_mask(done: torch.Tensor) -> torch.Tensor:
    """``[..., T]`` bool: step ``t`` belongs to the first episode (no ``done`` before ``t``).

    Examples:
        >>> import torch
        >>> from armeta_rl.collectors.episodes import valid_mask
        >>> valid_mask(torch.tensor([[False, True, False, True]]))
        tensor([[ True,  True, False, False]])
    """
    ended_before = done.cumsum(-1) - done.long()
    return ended_before == 0


class EpisodeCollector:
    """Collects ``[K, episodes, max_steps]`` trajectories for ``K`` tasks in any task-conditioned
    env of batch size ``[tasks, episodes]`` (point navigation, Ant goal, ...).

    Args:
        make_env: builds the env, called as ``make_env(batch_size=(K, episodes),
            max_steps=max_steps)``; the env reads the identifiers under ``"params"``
            (``TASK_KEY``) from the reset TensorDict and keeps them.
            In a Hydra config this is a ``_partial_: true`` node.
        episodes: episodes per task (the paper: 20).
        max_steps: episode length limit.
        device: where the trajectories are returned (the leader's device); the env steps on its
            own device.

    The returned TensorDict has batch ``[K, episodes, max_steps]`` and keys ``"observation"``,
    ``"action"``, ``"log_prob"`` (of the action under the collecting policy), ``"reward"``,
    ``"done"``, ``"terminated"``, ``"truncated"`` (``[..., 1]``), ``"mask"`` (bool, the step is part
    of the episode) and ``"params"`` (the task identifiers); and ``"reward_forward"`` where the
    env reports it (``FORWARD_REWARD``). The env is reseeded from torch's
    global RNG at every call, so ``torch.manual_seed`` (and a resumed checkpoint's RNG state) fixes
    the whole collection.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors.episodes import EpisodeCollector
        >>> from armeta_rl.envs import PointNavigationEnv
        >>> from armeta_rl.rl import GaussianMLP
        >>> _ = torch.manual_seed(0)
        >>> collector = EpisodeCollector(PointNavigationEnv, episodes=3, max_steps=5)
        >>> tasks = TensorDict({"params": torch.tensor([[0.3, -0.2], [-0.4, 0.1]])}, [2])
        >>> trajectories = collector.collect(tasks, policy=GaussianMLP(obs_dim=2, action_dim=2))
        >>> trajectories.batch_size  # [tasks, episodes, steps]
        torch.Size([2, 3, 5])
        >>> trajectories["observation"][0, 0]  # task 0's first episode: the point's positions
        tensor([[ 0.0000,  0.0000],
                [-0.1000,  0.1000],
                [ 0.0000,  0.2000],
                [-0.1000,  0.3000],
                [ 0.0000,  0.4000]])
        >>> trajectories["reward"][0, 0].flatten()  # -‖p' - g‖: (-0.1, 0.1) is 0.5 from the goal
        tensor([-0.5000, -0.5000, -0.6403, -0.6708, -0.8062])
    """

    def __init__(self, make_env: Callable[..., EnvBase], episodes: int = 20,
                 max_steps: int = 100, device: torch.device = CPU) -> None:
        if int(episodes) < 1:
            raise ConfigError("benchmark.collector.episodes", episodes, "must be >= 1")
        if int(max_steps) < 1:
            raise ConfigError("benchmark.collector.max_steps", max_steps, "must be >= 1")
        self.make_env = make_env
        self.episodes = int(episodes)
        self.max_steps = int(max_steps)
        self.device = device
        self._envs: dict[int, EnvBase] = {}

    def probe_env(self) -> EnvBase:
        """A one-episode env of batch size ``[1, 1]`` to check task boxes on."""
        return self.make_env(batch_size=(1, 1), max_steps=1)

    def _probe_sizes(self) -> tuple[int, int]:
        """The env's observation and action sizes, read from a probe env's specs (built under a
        forked RNG: reading them draws nothing from the run's stream)."""
        with torch.random.fork_rng(devices=[]):
            env = self.probe_env()
            try:
                return env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
            finally:
                env.close()

    @property
    def reports_forward_reward(self) -> bool:
        """Whether the env reports its forward reward after every step (``FORWARD_REWARD`` among
        its observation specs), so that the episodes carry it."""
        with torch.random.fork_rng(devices=[]):
            env = self.probe_env()
            try:
                return env.observation_spec.get(FORWARD_REWARD, None) is not None
            finally:
                env.close()

    @property
    def in_features(self) -> int:
        """Size of the policy's input: the env's ``"observation"``."""
        return self._probe_sizes()[0]

    @property
    def out_features(self) -> int:
        """Size of the policy's output: the env's action."""
        return self._probe_sizes()[1]

    def check_space(self, space: TaskSpace) -> None:
        """Refuse, before training, a task box the env cannot take: a probe env is reset at the
        box's two corners and its own identifier check decides (the identifiers an env allows
        form a box, so the corners stand for the whole box). The probe is built under a forked
        RNG, so the run's random stream is untouched."""
        dtype = torch.get_default_dtype()
        with torch.random.fork_rng(devices=[]):
            env = self.probe_env()
            try:
                for corner in (space.low, space.high):
                    params = torch.tensor(corner, dtype=dtype, device=env.device)
                    env.reset(TensorDict({TASK_KEY: params.expand(*env.batch_size, -1)},
                                         env.batch_size))
            except IdentifierError as error:
                box = {"names": list(space.names), "low": list(space.low),
                       "high": list(space.high)}
                raise ConfigError("benchmark.space", box,
                                  f"{type(env).__name__} refuses it: {error}") from None
            finally:
                env.close()

    def goal_references(self, params: torch.Tensor,
                        trajectories: TensorDictBase) -> dict[str, torch.Tensor] | None:
        """Per task ``[K]`` (float64), for the tasks ``params`` ``[K, d]`` and their episodes
        ``trajectories`` ``[K, E, T]``: ``"achieved"``, the goal term the episodes collected
        (their summed ``"reward_forward"``, the env's goal-dependent reward term, averaged over
        the episodes: :func:`episode_goal_terms`), ``"blind"``, that of the best goal-blind policy
        for this batch of tasks (the env class's ``blind_goal_term(params, steps)``: the best
        constant speed of the velocity families, standing at the goals' median for Ant-Pos), and
        ``"oracle"``, the best with the goal known (0: on target from the first step). ``None``
        where the env defines no goal-blind reference or reports no goal term."""
        blind = self._blind_goal_term()
        if blind is None or trajectories.get(FORWARD_REWARD, None) is None:
            return None
        achieved = episode_goal_terms(trajectories).to(torch.float64).mean(-1)
        reference = blind(params.to(achieved.device), self.max_steps).to(achieved)
        return {"achieved": achieved, "blind": reference, "oracle": torch.zeros_like(reference)}

    def _blind_goal_term(self) -> Callable[[torch.Tensor, int], torch.Tensor] | None:
        """The env class's ``blind_goal_term``, read once from a probe env (built under a
        forked RNG, transforms unwrapped); ``None`` if it has none."""
        if not hasattr(self, "_blind"):
            with torch.random.fork_rng(devices=[]):
                env = self.probe_env()
                try:
                    self._blind = getattr(type(_unwrapped(env)), "blind_goal_term", None)
                finally:
                    env.close()
        return self._blind

    def env(self, tasks: int) -> EnvBase:
        """The env of batch size ``[tasks, episodes]``, kept per batch shape (a value, not an
        object's identity). It carries nothing from one :meth:`collect` to the next: every call
        reseeds it and resets every entry with its task's identifiers, so keeping it changes no
        result and only spares rebuilding it (and, in the parallel and Ray collectors, its
        worker processes). It is built under a forked RNG, so building it draws nothing from the
        run's stream, or a resumed run (which builds it again) would draw once more than an
        uninterrupted one."""
        if tasks not in self._envs:
            with torch.random.fork_rng(devices=[]):
                self._envs[tasks] = self.make_env(batch_size=(tasks, self.episodes),
                                                  max_steps=self.max_steps)
        return self._envs[tasks]

    @torch.no_grad()
    def collect(
        self,
        tasks: TensorDictBase,
        policy_params: TensorDictBase | None = None,
        policy: GaussianMLP | None = None,
    ) -> TensorDict:
        """Roll out ``policy`` (with ``policy_params`` ``[K]`` if given, else its own parameters)
        for every task in ``tasks["params"]`` (identifiers ``[K, d]``)."""
        if policy is None:
            raise ValueError("EpisodeCollector.collect needs the policy network")
        n_tasks = tasks[TASK_KEY].shape[0]
        env = self.env(n_tasks)
        env_device = torch.device(env.device or "cpu")  # an env without one returns CPU tensors
        identifiers = tasks[TASK_KEY].to(env_device)
        env.set_seed(int(torch.randint(0, 2**62, ())))
        start = env.reset(TensorDict(
            {TASK_KEY: identifiers[:, None].expand(n_tasks, self.episodes, -1)}, env.batch_size))
        if next(policy.parameters()).device != env_device:
            policy = copy.deepcopy(policy).to(env_device)
            policy_params = None if policy_params is None else policy_params.to(env_device)
        # the env's own method only: TransformedEnv and batched envs forward unknown attributes
        # to the env(s) inside, whose transitions would skip the transforms (or fail)
        if callable(getattr(type(env), "gaussian_transitions", None)):
            rollout = env.gaussian_transitions(self.max_steps, policy, policy_params)
        else:
            rollout = env.rollout(self.max_steps, GaussianActor(policy, policy_params),
                                  tensordict=start, auto_reset=False, break_when_any_done=False)
        done = rollout["next", "done"].squeeze(-1)
        trajectories = TensorDict(
            {
                "observation": rollout["observation"],
                "action": rollout["action"],
                "log_prob": rollout["action_log_prob"],
                "reward": rollout["next", "reward"],
                "done": rollout["next", "done"],
                "terminated": rollout["next", "terminated"],
                "truncated": rollout["next", "truncated"],
                "mask": valid_mask(done),
                TASK_KEY: rollout[TASK_KEY],
                **({FORWARD_REWARD: rollout["next", FORWARD_REWARD]}
                   if ("next", FORWARD_REWARD) in rollout.keys(True) else {}),
            },
            batch_size=rollout.batch_size,
        )
        return trajectories if env_device == self.device else trajectories.to(self.device)


class PointNavigationCollector(EpisodeCollector):
    """:class:`EpisodeCollector` over :class:`PointNavigationEnv`.

    Args:
        episodes: episodes per task (the paper: 20).
        max_steps: episode length limit (100).
        sparse_regions: reward-scaling regions of the env (empty: plain navigation).
        squared_distance: reward minus the squared distance.
        seed: seed of the env (used only for goals that are never set).
        device: where the env steps and the trajectories are returned.
        truncated_regions: goal regions with the truncated (sparse) reward −min(dist, ρ).
        graphs: replay the rollouts as CUDA graphs (``None``: on CUDA;
            :class:`~armeta_rl.envs.point_navigation.PointNavigationEnv`).

    Examples:
        >>> import torch
        >>> from armeta_rl.collectors.episodes import PointNavigationCollector
        >>> collector = PointNavigationCollector(episodes=2, max_steps=100)
        >>> collector.reference_loss(torch.tensor([[0.5, 0.0], [0.0, 0.3]]))  # 0.4+0.3+0.2+0.1
        tensor([1.0000, 0.3000])
    """

    def __init__(self, episodes: int = 20, max_steps: int = 100,
                 sparse_regions: Sequence[Region] = (), squared_distance: bool = False,
                 seed: int | None = None, device: torch.device = CPU,
                 truncated_regions: Sequence[Region] = (), graphs: bool | None = None) -> None:
        if graphs is not None and not isinstance(graphs, bool):
            raise ConfigError("benchmark.collector.graphs", graphs, "true, false or null")
        self.sparse_regions = check_regions(sparse_regions)
        self.truncated_regions = check_regions(truncated_regions, TRUNCATED_KEY, "radius")
        self.squared_distance = bool(squared_distance)
        make_env = partial(PointNavigationEnv, sparse_regions=self.sparse_regions,
                           squared_distance=self.squared_distance, seed=seed, device=device,
                           truncated_regions=self.truncated_regions, graphs=graphs)
        super().__init__(make_env, episodes, max_steps, device)

    def reference_loss(self, params: torch.Tensor) -> torch.Tensor:
        """Minus the best return any policy gets on each goal ``[K, 2]`` in an episode (the
        straight path at full speed, :func:`~armeta_rl.envs.point_navigation.reference_return`):
        the reference L* of the adversary's regret ``risk.ar.signal=regret``."""
        return -reference_return(params, self.max_steps, self.sparse_regions,
                                 self.truncated_regions, self.squared_distance)

    def goal_references(self, params: torch.Tensor,
                        trajectories: TensorDictBase) -> dict[str, torch.Tensor]:
        """Per goal ``[K]`` (float64), for goals ``params`` ``[K, 2]`` and their episodes
        ``[K, E, T]``: ``"achieved"``, the episodes' mean return (the reward is all goal term),
        ``"blind"``, the return of the one fixed path best on average over the batch
        (:func:`~armeta_rl.envs.point_navigation.blind_return`), and ``"oracle"``, the best
        return of any policy (:meth:`reference_loss`'s straight path at full speed)."""
        achieved = episode_returns(trajectories).to(torch.float64).mean(-1)
        goals = params.to(achieved)
        regions = (self.max_steps, self.sparse_regions, self.truncated_regions,
                   self.squared_distance)
        return {"achieved": achieved, "blind": blind_return(goals, *regions),
                "oracle": reference_return(goals, *regions)}


def episode_returns(trajectories: TensorDictBase) -> torch.Tensor:
    """Undiscounted return of every episode ``[K, episodes]``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors.episodes import episode_returns
        >>> reward = torch.tensor([[[-1.0, -0.5, -9.0]]]).unsqueeze(-1)  # [K=1, episodes=1, T=3, 1]
        >>> mask = torch.tensor([[[True, True, False]]])  # the episode ended after two steps
        >>> episode_returns(TensorDict({"reward": reward, "mask": mask}, [1, 1, 3]))
        tensor([[-1.5000]])
    """
    reward = trajectories["reward"].squeeze(-1)
    return (reward * trajectories["mask"]).sum(-1)


def episode_goal_terms(trajectories: TensorDictBase) -> torch.Tensor:
    """The goal term of every episode ``[K, episodes]``: its summed ``"reward_forward"`` (the
    env's goal-dependent reward term, :data:`~armeta_rl.tasks.protocol.FORWARD_REWARD`) over
    its steps, the return less its goal-independent parts (control and contact costs, alive
    bonus).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors.episodes import episode_goal_terms
        >>> forward = torch.tensor([[[-0.5, -0.25, -9.0]]]).unsqueeze(-1)  # [K=1, E=1, T=3, 1]
        >>> mask = torch.tensor([[[True, True, False]]])
        >>> episode_goal_terms(TensorDict({"reward_forward": forward, "mask": mask}, [1, 1, 3]))
        tensor([[-0.7500]])
    """
    forward = trajectories[FORWARD_REWARD].squeeze(-1)
    return (forward * trajectories["mask"]).sum(-1)


def _unwrapped(env: EnvBase) -> EnvBase:
    """The env under every ``TransformedEnv`` wrapping ``env`` (a physics family's
    transform), where its class's task attributes are."""
    while isinstance(env, TransformedEnv):
        env = env.base_env
    return env
