"""2-D point-robot navigation (paper, appendix "Meta Learning Continuous Control"; MAML's
"2DNavigation", as in pytorch-maml-rl and CAVIA), batched over ``[tasks, episodes]``.

The robot starts at the origin and observes only its own position; the goal is hidden and must be
inferred from rewards. An action is a velocity clipped to ``[-0.1, 0.1]`` per axis; the reward is
minus the distance to the goal after the move (or minus its square). An episode ends when the
robot is within 0.01 of the goal on both axes, or after ``max_steps`` steps.

Sparse-reward regions. The paper discounts "the step-wise reward by 0.6 to area
[-0.25,-0.5]×[0.25,0.5] and 0.4 to area [0.25,0.5]×[-0.25,-0.5]". We read each area as
x-interval × y-interval with its endpoints sorted, i.e. goals with x ∈ [-0.5, -0.25] and
y ∈ [0.25, 0.5] (top-left corner) have every step reward multiplied by 0.6, and goals with
x ∈ [0.25, 0.5], y ∈ [-0.5, -0.25] (bottom-right corner) by 0.4. The scale depends on the *task*
(the goal), not on where the robot is. :data:`PAPER_SPARSE_REGIONS` holds this list; an empty list
gives plain navigation.

Scaled regions are not harder to adapt to: MAML-TRPO normalizes each task's advantages, so a task
whose rewards are all scaled by 0.4 gets the same inner and outer steps as unscaled, only a return
0.4 times as large (docs/meta-rl.md measures it). *Truncated regions* make a region hard instead:
goals there give the reward −min(‖p − g‖, ρ) (``truncated_regions`` entries ``((x_low, x_high),
(y_low, y_high), ρ)``), constant farther than ρ from the goal, so only episodes that come within ρ
of it say where it is: a sparse reward, as PEARL's sparse point robot, on the dense reward's scale
(``point_nav_sparse``).

:func:`reference_return` is the best return any policy gets on a goal, that of the straight
path at full speed, in closed form: the reference of the adversary's regret signal.
:func:`blind_return` is the best a policy that does not know the goal gets on a batch of goals:
one fixed path, to the point best on average over the batch (:func:`blind_point`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import partial

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from armeta_rl.cuda_graphs import GraphedCall
from armeta_rl.errors import ConfigError
from armeta_rl.rl.policy import GaussianMLP
from armeta_rl.rl.policy import act as policy_act
from armeta_rl.tasks.distributions import TaskEnvMixin
from armeta_rl.tasks.protocol import TASK_KEY

Region = tuple[tuple[float, float], tuple[float, float], float]
"""((x_low, x_high), (y_low, y_high), reward_scale)."""

PAPER_SPARSE_REGIONS: tuple[Region, ...] = (
    ((-0.5, -0.25), (0.25, 0.5), 0.6),
    ((0.25, 0.5), (-0.5, -0.25), 0.4),
)

GOAL_LOW, GOAL_HIGH = -0.5, 0.5
GOAL_NAMES = ("goal_x", "goal_y")
MAX_SPEED = 0.1
GOAL_TOLERANCE = 0.01
REGIONS_KEY = "benchmark.collector.sparse_regions"
TRUNCATED_KEY = "benchmark.collector.truncated_regions"


def check_regions(regions: Sequence[Region], key: str = REGIONS_KEY,
                  value: str = "scale") -> tuple[Region, ...]:
    """``regions`` as floats; :class:`ConfigError` naming ``key`` for an entry that is not
    ``[[xlo, xhi], [ylo, yhi], value]`` with xlo < xhi, ylo < yhi and value >= 0."""
    checked = []
    for region in regions:
        try:
            (x_low, x_high), (y_low, y_high), scale = region
            x_low, x_high, y_low, y_high, scale = map(float, (x_low, x_high, y_low, y_high, scale))
        except (TypeError, ValueError) as error:
            raise ConfigError(key, region, f"entries: [[xlo, xhi], [ylo, yhi], {value}]") from error
        if not (x_low < x_high and y_low < y_high and scale >= 0):
            raise ConfigError(key, region, f"needs xlo < xhi, ylo < yhi and {value} >= 0")
        checked.append(((x_low, x_high), (y_low, y_high), scale))
    return tuple(checked)


def goal_region_value(goal: torch.Tensor, regions: Sequence[Region],
                      default: float = 1.0) -> torch.Tensor:
    """Per-task value ``[...]`` for goals ``[..., 2]``: the value of the first region that
    contains the goal (closed box), ``default`` elsewhere."""
    value = torch.full(goal.shape[:-1], default, dtype=goal.dtype, device=goal.device)
    for (x_low, x_high), (y_low, y_high), region_value in reversed(tuple(regions)):
        x, y = goal[..., 0], goal[..., 1]
        inside = (x >= x_low) & (x <= x_high) & (y >= y_low) & (y <= y_high)
        value = torch.where(inside, torch.full_like(value, region_value), value)
    return value


def goal_reward_scale(goal: torch.Tensor, regions: Sequence[Region]) -> torch.Tensor:
    """Per-task reward scale ``[...]`` for goals ``[..., 2]``: the scale of the first region that
    contains the goal (closed box), 1 elsewhere."""
    return goal_region_value(goal, regions)


def goal_distance_cap(goal: torch.Tensor, regions: Sequence[Region],
                      squared_distance: bool = False) -> torch.Tensor:
    """Per-task cap ``[...]`` on the distance the reward feels, for goals ``[..., 2]``: ρ (ρ²
    for the squared distance) of the first truncated region that contains the goal, ∞
    elsewhere."""
    cap = goal_region_value(goal, regions, math.inf)
    return cap.square() if squared_distance else cap


def step_reward(offset: torch.Tensor, scale: torch.Tensor, cap: torch.Tensor,
                squared_distance: bool) -> torch.Tensor:
    """The step reward −scale·min(dist, cap) ``[..., 1]`` of offsets p − g ``[..., 2]``, dist
    the distance ‖p − g‖ (or its square); ``scale`` and ``cap`` ``[..., 1]``."""
    squared = offset.square().sum(-1, keepdim=True)
    distance = squared if squared_distance else squared.sqrt()
    return -scale * torch.minimum(distance, cap)


def move(position: torch.Tensor, steps: torch.Tensor, action: torch.Tensor, goal: torch.Tensor,
         scale: torch.Tensor, cap: torch.Tensor, squared_distance: bool, max_steps: int
         ) -> tuple[torch.Tensor, ...]:
    """One step from ``position`` ``[*batch, 2]`` after ``steps`` ``[*batch, 1]`` steps toward
    ``goal`` with reward ``scale`` and ``cap`` (:func:`step_reward`): the new position and step
    count, the reward, and whether the episode terminates (goal reached) or is truncated (time
    limit)."""
    position = position + action.clamp(-MAX_SPEED, MAX_SPEED)
    steps = steps + 1
    offset = position - goal
    reward = step_reward(offset, scale, cap, squared_distance)
    terminated = (offset.abs() < GOAL_TOLERANCE).all(-1, keepdim=True)
    return position, steps, reward, terminated, steps >= max_steps


def roll(act: Callable[[torch.Tensor], dict], n_steps: int, position: torch.Tensor,
         counts: torch.Tensor, goal: torch.Tensor, scale: torch.Tensor, cap: torch.Tensor,
         squared_distance: bool, max_steps: int) -> dict:
    """``n_steps`` steps of :func:`move` from ``position`` and ``counts`` ``[*batch, ...]``,
    ``act(observation)`` choosing each step's ``"action"`` (with whatever else it returns).
    Finished episodes restart from the origin between steps, as TorchRL's automatic partial
    reset restarts them (never after the last step).

    Returns the steps stacked along a time dimension after the batch ``[*batch, n_steps, ...]``:
    ``"observation"`` and ``act``'s outputs, and ``("next", key)`` for ``"observation"``,
    ``"reward"``, ``"done"``, ``"terminated"``, ``"truncated"``; and ``"position"``,
    ``"counts"``, the state after the last step.
    """
    acted, moved = [], []
    for t in range(n_steps):
        observation = position.clone()
        acted.append({"observation": observation, **act(observation)})
        new_position, counts, reward, terminated, truncated = move(
            position, counts, acted[-1]["action"], goal, scale, cap, squared_distance, max_steps)
        done = terminated | truncated
        moved.append({"observation": new_position.clone(), "reward": reward, "done": done,
                      "terminated": terminated, "truncated": truncated})
        position = new_position
        if t < n_steps - 1:  # unconditionally: asking whether any is done would wait for a GPU
            position = torch.where(done, torch.zeros_like(position), position)
            counts = torch.where(done, torch.zeros_like(counts), counts)
    dim = position.dim() - 1
    arrays = {key: torch.stack([step[key] for step in acted], dim) for key in acted[0]}
    arrays.update({("next", key): torch.stack([step[key] for step in moved], dim)
                   for key in moved[0]})
    return {**arrays, "position": new_position, "counts": counts}


def gaussian_episode(net: GaussianMLP, names: tuple[str, ...], per_task: bool, n_steps: int,
                     squared_distance: bool, max_steps: int, position: torch.Tensor,
                     counts: torch.Tensor, goal: torch.Tensor, scale: torch.Tensor,
                     cap: torch.Tensor, *values: torch.Tensor) -> dict:
    """:func:`roll` with the Gaussian policy ``net`` acting under the parameters ``values``
    (named ``names``; per task or shared, :func:`~armeta_rl.rl.policy.act`): a function of
    tensors alone, what a CUDA graph of the rollout replays."""
    params = dict(zip(names, values))
    return roll(lambda observation: policy_act(net, params, observation, per_task), n_steps,
                position, counts, goal, scale, cap, squared_distance, max_steps)


def reference_return(goal: torch.Tensor, max_steps: int, sparse_regions: Sequence[Region] = (),
                     truncated_regions: Sequence[Region] = (),
                     squared_distance: bool = False) -> torch.Tensor:
    """The best return ``[...]`` any policy gets on goals ``[..., 2]``: that of moving every
    coordinate toward the goal at full speed, in closed form.

    From the origin, after t steps each coordinate is at most 0.1·t from 0, and the full-speed
    path is at the point of that box nearest the goal, offset max(|g_i| − 0.1·t, 0) per axis: no
    policy is nearer at any step, every reward decreases with the distance and is ≤ 0, and this
    path ends (within 0.01 of the goal) first, so its return is the largest.
    """
    steps = torch.arange(1, max_steps + 1, dtype=goal.dtype, device=goal.device)
    offset = (goal.abs().unsqueeze(-2) - MAX_SPEED * steps.unsqueeze(-1)).clamp(min=0)
    scale = goal_reward_scale(goal, sparse_regions)[..., None, None]
    cap = goal_distance_cap(goal, truncated_regions, squared_distance)[..., None, None]
    reward = step_reward(offset, scale, cap, squared_distance).squeeze(-1)
    reached = (offset < GOAL_TOLERANCE).all(-1)
    before_end = (reached.cumsum(-1) - reached.long()) == 0
    return (reward * before_end).sum(-1)


def fixed_path_return(point: torch.Tensor, goal: torch.Tensor, max_steps: int,
                      sparse_regions: Sequence[Region] = (),
                      truncated_regions: Sequence[Region] = (),
                      squared_distance: bool = False) -> torch.Tensor:
    """The return ``[...]`` on goals ``[..., 2]`` of one fixed path, the same whatever the goal:
    every coordinate moves toward ``point`` ``[..., 2]`` (broadcast against ``goal``) at full
    speed, then the robot stays there; the episode ends as the env ends it (within 0.01 of the
    goal on both axes, or after ``max_steps``).

    After t steps the robot is at sign(m)·min(|m|, 0.1·t) per axis. With ``point = goal`` this
    is the full-speed path of :func:`reference_return`, the best return of any policy; with
    one point for every goal it is a goal-blind policy's return (:func:`blind_return`). The
    steps until every point is reached are summed one by one, the rest in closed form: the robot
    stays, so each of them has the reward of the last step summed, unless the episode ended."""
    point = point.to(goal)
    moving = min(max_steps, math.ceil(float(point.abs().max()) / MAX_SPEED) + 1)
    steps = torch.arange(1, moving + 1, dtype=goal.dtype, device=goal.device)
    path = point.sign().unsqueeze(-2) * torch.minimum(
        point.abs().unsqueeze(-2), MAX_SPEED * steps.unsqueeze(-1))
    offset = path - goal.unsqueeze(-2)
    scale = goal_reward_scale(goal, sparse_regions)[..., None, None]
    cap = goal_distance_cap(goal, truncated_regions, squared_distance)[..., None, None]
    reward = step_reward(offset, scale, cap, squared_distance).squeeze(-1)
    reached = (offset.abs() < GOAL_TOLERANCE).all(-1)
    before_end = (reached.cumsum(-1) - reached.long()) == 0
    staying = (max_steps - moving) * reward[..., -1] * ~reached.any(-1)
    return (reward * before_end).sum(-1) + staying


BLIND_SEARCH_POINTS = 21
"""Grid points per axis in each round of :func:`blind_point`'s search."""
BLIND_SEARCH_ROUNDS = 3
"""Rounds of :func:`blind_point`'s search: each narrows the grid to two cells of the last one
around its best point (a spacing of 0.05, 0.005 and 0.0005 on the goal box)."""
BLIND_SEARCH_CHUNK = 64
"""Candidate points scored at once by :func:`blind_point` (bounds its memory)."""


def blind_point(goal: torch.Tensor, max_steps: int, sparse_regions: Sequence[Region] = (),
                truncated_regions: Sequence[Region] = (), squared_distance: bool = False,
                weights: torch.Tensor | None = None) -> torch.Tensor:
    """The point m ``[2]`` of the goal box whose fixed path (:func:`fixed_path_return`) has the
    largest mean return over the goals ``[K, 2]`` (weighted by ``weights`` ``[K]`` if given): the
    best goal-blind policy of this kind for the batch, found by a coarse-to-fine grid search
    (:data:`BLIND_SEARCH_POINTS` per axis, :data:`BLIND_SEARCH_ROUNDS` rounds). With the plain
    reward and a long horizon m is near the goals' geometric median; the search also handles the
    regions' scales and caps, the squared distance and the episode's end at the goal."""
    goal = goal.to(torch.float64)
    weights = (torch.ones(len(goal), dtype=goal.dtype, device=goal.device) if weights is None
               else weights.to(goal))
    centre = torch.zeros(2, dtype=goal.dtype, device=goal.device)
    half_width = (GOAL_HIGH - GOAL_LOW) / 2
    offsets = torch.linspace(-1.0, 1.0, BLIND_SEARCH_POINTS, dtype=goal.dtype, device=goal.device)
    for _ in range(BLIND_SEARCH_ROUNDS):
        axis = (centre.unsqueeze(-1) + half_width * offsets).clamp(GOAL_LOW, GOAL_HIGH)
        candidates = torch.stack(torch.meshgrid(axis[0], axis[1], indexing="ij"), -1)
        candidates = candidates.reshape(-1, 2)
        means = torch.cat([
            fixed_path_return(chunk[:, None], goal, max_steps, sparse_regions,
                              truncated_regions, squared_distance) @ weights
            for chunk in candidates.split(BLIND_SEARCH_CHUNK)]) / weights.sum()
        centre = candidates[means.argmax()]
        half_width *= 2 / (BLIND_SEARCH_POINTS - 1)
    return centre


def blind_return(goal: torch.Tensor, max_steps: int, sparse_regions: Sequence[Region] = (),
                 truncated_regions: Sequence[Region] = (),
                 squared_distance: bool = False) -> torch.Tensor:
    """R_blind ``[K]`` (float64) on goals ``[K, 2]``: on each goal, the return of the one fixed
    path that is best on average over the batch (:func:`blind_point`): the reference a policy
    that does not know the goal can reach, against which an adapted policy's return says how
    much of the gap to :func:`reference_return` adaptation closes. Repeated goals (the R copies
    of a task) weigh as often as they occur."""
    goal = goal.to(torch.float64)
    unique, counts = torch.unique(goal, dim=0, return_counts=True)
    point = blind_point(unique, max_steps, sparse_regions, truncated_regions, squared_distance,
                        counts)
    return fixed_path_return(point, goal, max_steps, sparse_regions, truncated_regions,
                             squared_distance)


class PointNavigationEnv(TaskEnvMixin, EnvBase):
    """Point-robot navigation with batch size ``[tasks, episodes]`` (pure batched torch).

    The goal of every batch entry is set through ``"params"`` (:data:`~armeta_rl.tasks.TASK_KEY`,
    shape ``[*batch, 2]``: goal_x, goal_y) in the reset TensorDict and is kept in the env's state,
    so automatic (partial) resets inside ``env.rollout`` or a collector keep each entry's task. A
    reset without ``"params"`` keeps the current goals; goals that were never set are drawn
    uniformly from ``[-0.5, 0.5]²`` with the env's seeded generator. Goals under another key
    (``"goal"``), of another width or outside ``[-0.5, 0.5]²`` raise
    :class:`~armeta_rl.errors.IdentifierError`. ``"params"`` is also emitted with every
    observation, so trajectories carry their task; policies read only ``"observation"``.

    Args:
        batch_size: ``[tasks, episodes]`` (any batch shape works).
        max_steps: time limit; reaching it sets ``"truncated"``.
        sparse_regions: list of ``((xlo, xhi), (ylo, yhi), scale)``; see the module docstring.
        truncated_regions: list of ``((xlo, xhi), (ylo, yhi), ρ)``: goals there give the
            reward −min(‖p − g‖, ρ) (squared: −min(‖p − g‖², ρ²)); see the module docstring.
        squared_distance: reward ``-‖p - g‖²`` instead of ``-‖p - g‖``.
        seed: seed of the generator that draws default goals.
        device: torch device.
        graphs: replay :meth:`gaussian_transitions` as CUDA graphs (``None``: on CUDA).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import PointNavigationEnv
        >>> from armeta_rl.tasks import TASK_KEY
        >>> env = PointNavigationEnv(batch_size=(1, 1), seed=0)  # starts at (0, 0)
        >>> goal = torch.tensor([[[0.3, -0.2]]])
        >>> start = env.reset(TensorDict({TASK_KEY: goal}, [1, 1]))
        >>> diagonal = lambda td: td.set("action", torch.tensor([[[0.1, -0.1]]]))
        >>> steps = env.rollout(3, diagonal, tensordict=start, auto_reset=False)
        >>> steps["next", "observation"].squeeze()  # past the goal's y at the third step
        tensor([[ 0.1000, -0.1000],
                [ 0.2000, -0.2000],
                [ 0.3000, -0.3000]])
        >>> steps["next", "reward"].flatten()  # -‖p - g‖: -√0.05, -0.1, -0.1
        tensor([-0.2236, -0.1000, -0.1000])
    """

    identifier_names = GOAL_NAMES
    task_boxes = {name: (GOAL_LOW, GOAL_HIGH) for name in GOAL_NAMES}
    identifier_low, identifier_high = GOAL_LOW, GOAL_HIGH

    def __init__(
        self,
        batch_size: Sequence[int] = (1, 1),
        max_steps: int = 100,
        sparse_regions: Sequence[Region] = (),
        squared_distance: bool = False,
        seed: int | None = None,
        device: torch.device | str = "cpu",
        truncated_regions: Sequence[Region] = (),
        graphs: bool | None = None,
        require_identifiers: bool = False,
    ) -> None:
        if int(max_steps) < 1:
            raise ConfigError("benchmark.collector.max_steps", max_steps, "must be >= 1")
        super().__init__(device=device, batch_size=torch.Size(batch_size))
        self.max_steps = int(max_steps)
        self.require_identifiers = bool(require_identifiers)
        self.sparse_regions = check_regions(sparse_regions)
        self.truncated_regions = check_regions(truncated_regions, TRUNCATED_KEY, "radius")
        self.squared_distance = bool(squared_distance)
        shape = self.batch_size
        dtype = torch.get_default_dtype()
        goal = Bounded(GOAL_LOW, GOAL_HIGH, shape=(*shape, 2), dtype=dtype, device=self.device)
        self.observation_spec = Composite(
            {"observation": Unbounded(shape=(*shape, 2), dtype=dtype, device=self.device),
             TASK_KEY: goal},
            shape=shape,
            device=self.device,
        )
        # The goal is also a state entry, so that TransformedEnv (which passes only reset and
        # state keys to the base env's reset) forwards it; the env's own copy stays authoritative.
        self.state_spec = Composite({TASK_KEY: goal.clone()}, shape=shape, device=self.device)
        self.action_spec = Bounded(
            -MAX_SPEED, MAX_SPEED, shape=(*shape, 2), dtype=dtype, device=self.device
        )
        self.reward_spec = Unbounded(shape=(*shape, 1), dtype=dtype, device=self.device)
        self.done_spec = Composite(
            done=Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=self.device),
            terminated=Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=self.device),
            truncated=Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=self.device),
            shape=shape,
            device=self.device,
        )
        self._generator = torch.Generator(device=self.device)
        self._set_seed(seed)
        self._position = torch.zeros(*shape, 2, dtype=dtype, device=self.device)
        self._goal = self._draw_goals(shape, dtype)
        self._set_goal_rewards()
        self._steps = torch.zeros(*shape, 1, dtype=torch.long, device=self.device)
        self.graphs = self.device.type == "cuda" and (graphs is None or bool(graphs))
        self._graphed: dict[tuple, tuple[GaussianMLP, Callable[..., dict]]] = {}

    def _set_goal_rewards(self) -> None:
        """Each entry's reward scale and distance cap ``[*batch, 1]`` from its goal."""
        self._scale = goal_reward_scale(self._goal, self.sparse_regions).unsqueeze(-1)
        self._cap = goal_distance_cap(
            self._goal, self.truncated_regions, self.squared_distance).unsqueeze(-1)

    def _draw_goals(self, shape: torch.Size, dtype: torch.dtype) -> torch.Tensor:
        unit = torch.rand(*shape, 2, generator=self._generator, device=self.device)
        return (GOAL_LOW + (GOAL_HIGH - GOAL_LOW) * unit).to(dtype)

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self._generator.manual_seed(int(seed))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        shape = self.batch_size
        reset = None if tensordict is None else tensordict.get("_reset", None)
        if reset is None:
            reset = torch.ones(*shape, 1, dtype=torch.bool, device=self.device)
        mask = reset.reshape(*shape, 1)
        goal = self.identifier_check.read(tensordict, shape)
        if goal is not None:
            goal = goal.to(self._goal.dtype).expand_as(self._goal)
            self._goal = torch.where(mask, goal, self._goal)
            self._set_goal_rewards()
        self._position = torch.where(mask, torch.zeros_like(self._position), self._position)
        self._steps = torch.where(mask, torch.zeros_like(self._steps), self._steps)
        false = torch.zeros(*shape, 1, dtype=torch.bool, device=self.device)
        return TensorDict(
            {
                "observation": self._position.clone(),
                TASK_KEY: self._goal.clone(),
                "done": false,
                "terminated": false.clone(),
                "truncated": false.clone(),
            },
            batch_size=shape,
            device=self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self._position, self._steps, reward, terminated, truncated = move(
            self._position, self._steps, tensordict.get("action"), self._goal, self._scale,
            self._cap, self.squared_distance, self.max_steps)
        return TensorDict(
            {
                "observation": self._position.clone(),
                TASK_KEY: self._goal.clone(),
                "reward": reward,
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def transitions(self, steps: int,
                    policy: Callable[[TensorDictBase], TensorDictBase]) -> TensorDict:
        """``env.rollout(steps, policy, auto_reset=False, break_when_any_done=False)`` from the
        env's current state (after a reset), without TorchRL's per-step env machinery, which
        costs far more than this env's physics.

        ``policy`` reads ``"observation"`` from a TensorDict and writes ``"action"`` and whatever
        else it writes (a TorchRL actor: ``"action_log_prob"``, ``"loc"``, ...); it is called once
        a step, as ``env.rollout`` calls it, so it draws the same random actions. Finished
        episodes restart from the origin between steps (:func:`roll`). Equal to ``env.rollout``
        transition for transition, bit for bit (``tests/test_point_navigation.py``).

        Returns a TensorDict ``[*batch, steps]`` with ``"observation"``, ``"params"``, the
        policy's outputs, and ``"next"``: ``"observation"``, ``"params"``, ``"reward"``,
        ``"done"``, ``"terminated"``, ``"truncated"``.
        """
        batch = self.batch_size

        def act(observation: torch.Tensor) -> dict:
            acted = policy(TensorDict({"observation": observation}, batch, device=self.device))
            return dict(acted.exclude("observation").items(True, True))

        n_steps = int(steps)
        return self._rollout(roll(act, n_steps, self._position, self._steps, self._goal,
                                  self._scale, self._cap, self.squared_distance,
                                  self.max_steps), n_steps)

    def gaussian_transitions(self, steps: int, net: GaussianMLP,
                             params: TensorDictBase | None = None) -> TensorDict:
        """:meth:`transitions` with :class:`~armeta_rl.rl.policy.GaussianActor` ``(net,
        params)``, the same rollout bit for bit, computed by a function of tensors alone (the
        env's state, the policy's parameters) that the env replays as a CUDA graph when its
        ``graphs`` is on (:class:`~armeta_rl.cuda_graphs.GraphedCall`): the rollout's thousands
        of small kernels cost one launch."""
        per_task = params is not None
        named = params.flatten_keys(".").to_dict() if per_task else {
            name: value.detach() for name, value in net.named_parameters()}
        key = (int(steps), per_task, tuple(named))
        kept = self._graphed.get(key)
        if kept is None or kept[0] is not net:  # a new net replaces the old one's graph
            episode = partial(gaussian_episode, net, tuple(named), per_task, int(steps),
                              self.squared_distance, self.max_steps)
            kept = self._graphed[key] = (net, GraphedCall(episode) if self.graphs else episode)
        arrays = kept[1](self._position, self._steps, self._goal, self._scale, self._cap,
                         *named.values())
        return self._rollout(arrays, int(steps))

    def _rollout(self, arrays: dict, n_steps: int) -> TensorDict:
        """The TensorDict of :func:`roll`'s ``arrays``, with the goals; the env's state moves to
        where the rollout left it."""
        arrays = dict(arrays)
        self._position, self._steps = arrays.pop("position"), arrays.pop("counts")
        batch = self.batch_size
        goal = self._goal.unsqueeze(len(batch)).expand(*batch, n_steps, 2)
        rollout = TensorDict(arrays, [*batch, n_steps], device=self.device)
        rollout.update({TASK_KEY: goal.clone(), ("next", TASK_KEY): goal.clone()})
        return rollout
