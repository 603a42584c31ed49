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
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from armeta_rl.errors import ConfigError
from armeta_rl.tasks.protocol import TASK_KEY, read_identifiers

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


def check_regions(regions: Sequence[Region]) -> tuple[Region, ...]:
    checked = []
    for region in regions:
        try:
            (x_low, x_high), (y_low, y_high), scale = region
            x_low, x_high, y_low, y_high, scale = map(float, (x_low, x_high, y_low, y_high, scale))
        except (TypeError, ValueError) as error:
            raise ConfigError(
                REGIONS_KEY, region, "entries: [[xlo, xhi], [ylo, yhi], scale]"
            ) from error
        if not (x_low < x_high and y_low < y_high and scale >= 0):
            raise ConfigError(
                REGIONS_KEY, region, "needs xlo < xhi, ylo < yhi and scale >= 0"
            )
        checked.append(((x_low, x_high), (y_low, y_high), scale))
    return tuple(checked)


def goal_reward_scale(goal: torch.Tensor, regions: Sequence[Region]) -> torch.Tensor:
    """Per-task reward scale ``[...]`` for goals ``[..., 2]``: the scale of the first region that
    contains the goal (closed box), 1 elsewhere."""
    scale = torch.ones(goal.shape[:-1], dtype=goal.dtype, device=goal.device)
    for (x_low, x_high), (y_low, y_high), region_scale in reversed(tuple(regions)):
        x, y = goal[..., 0], goal[..., 1]
        inside = (x >= x_low) & (x <= x_high) & (y >= y_low) & (y <= y_high)
        scale = torch.where(inside, torch.full_like(scale, region_scale), scale)
    return scale


class PointNavigationEnv(EnvBase):
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
        squared_distance: reward ``-‖p - g‖²`` instead of ``-‖p - g‖``.
        seed: seed of the generator that draws default goals.
        device: torch device.
    """

    def __init__(
        self,
        batch_size: Sequence[int] = (1, 1),
        max_steps: int = 100,
        sparse_regions: Sequence[Region] = (),
        squared_distance: bool = False,
        seed: int | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        if int(max_steps) < 1:
            raise ConfigError("benchmark.collector.max_steps", max_steps, "must be >= 1")
        super().__init__(device=device, batch_size=torch.Size(batch_size))
        self.max_steps = int(max_steps)
        self.sparse_regions = check_regions(sparse_regions)
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
        self._scale = goal_reward_scale(self._goal, self.sparse_regions).unsqueeze(-1)
        self._steps = torch.zeros(*shape, 1, dtype=torch.long, device=self.device)

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
        goal = read_identifiers(tensordict, GOAL_NAMES, GOAL_LOW, GOAL_HIGH, shape)
        if goal is not None:
            goal = goal.to(self._goal.dtype).expand_as(self._goal)
            self._goal = torch.where(mask, goal, self._goal)
            self._scale = goal_reward_scale(self._goal, self.sparse_regions).unsqueeze(-1)
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

    def _move(self, position: torch.Tensor, steps: torch.Tensor, action: torch.Tensor
              ) -> tuple[torch.Tensor, ...]:
        """One step from ``position`` ``[*batch, 2]`` after ``steps`` ``[*batch, 1]`` steps, a pure
        function under the env's goals: the new position and step count, the reward, and
        whether the episode terminates (goal reached) or is truncated (time limit)."""
        position = position + action.clamp(-MAX_SPEED, MAX_SPEED)
        steps = steps + 1
        offset = position - self._goal
        squared = offset.square().sum(-1, keepdim=True)
        distance = squared if self.squared_distance else squared.sqrt()
        reward = -distance * self._scale
        terminated = (offset.abs() < GOAL_TOLERANCE).all(-1, keepdim=True)
        return position, steps, reward, terminated, steps >= self.max_steps

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self._position, self._steps, reward, terminated, truncated = self._move(
            self._position, self._steps, tensordict.get("action"))
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
        episodes restart from the origin between steps, as TorchRL's automatic partial reset
        restarts them (never after the last step). Equal to ``env.rollout`` transition for
        transition, bit for bit (``tests/test_point_navigation.py``).

        Returns a TensorDict ``[*batch, steps]`` with ``"observation"``, ``"params"``, the
        policy's outputs, and ``"next"``: ``"observation"``, ``"params"``, ``"reward"``,
        ``"done"``, ``"terminated"``, ``"truncated"``.
        """
        batch, n_steps = self.batch_size, int(steps)
        position, counts = self._position, self._steps
        acted, moved = [], []
        for t in range(n_steps):
            observed = TensorDict({"observation": position.clone()}, batch, device=self.device)
            acted.append(policy(observed))
            new_position, counts, reward, terminated, truncated = self._move(
                position, counts, acted[-1].get("action"))
            done = terminated | truncated
            moved.append({"observation": new_position.clone(), "reward": reward, "done": done,
                          "terminated": terminated, "truncated": truncated})
            position = new_position
            if t < n_steps - 1 and bool(done.any()):
                position = torch.where(done, torch.zeros_like(position), position)
                counts = torch.where(done, torch.zeros_like(counts), counts)
        self._position, self._steps = new_position, counts
        dim = len(batch)
        rollout = torch.stack(acted, dim)
        goal = self._goal.unsqueeze(dim).expand(*batch, n_steps, 2)
        after = {key: torch.stack([step[key] for step in moved], dim) for key in moved[0]}
        rollout.update({TASK_KEY: goal.clone(), "next": {**after, TASK_KEY: goal.clone()}})
        return rollout
