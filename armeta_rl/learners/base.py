"""The leader protocol (docs/architecture.md): MAML, CNP and MAML-TRPO all implement it; and
the model sizes a leader takes from its collector (:func:`sizes`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import torch
from tensordict import TensorDict
from torch import Tensor, nn

from armeta_rl.collectors.base import TaskCollector

TaskWeights = Callable[[Tensor], Tensor]
"""Maps detached per-task losses ``[K]`` to non-negative weights ``[K]`` that sum to one."""


def weighted_sum(weights: Tensor, per_task: Tensor) -> Tensor:
    """Σ_k w_k x_k over the tasks of a batch: with x_k = L_k the leader's objective, the Monte
    Carlo average of paper Eq. (15) for w_k = 1/K and its reweighted forms for the other
    principles (Eqs. (19) and (21)); MAML-TRPO also weighs its per-task KL constraint with it."""
    return (weights * per_task).sum()


def mean_squared_error(prediction: Tensor, target: Tensor,
                       dim: int | tuple[int, ...] | None = None) -> Tensor:
    """The regression risk L(D; θ) (paper Sec. 2, "in regression"): the mean of
    (prediction − target)² over all entries, or over ``dim`` (one value per task)."""
    error = (prediction - target).pow(2)
    return error.mean() if dim is None else error.mean(dim)


@runtime_checkable
class Leader(Protocol):
    """The meta-learner θ: collects data for the tasks, adapts, scores and updates itself.

    The game loop hands the data on in the open: ``data = collect(tasks)``, then
    ``step(data, weights)``, then ``evaluate(data)`` for the follower; no call reads what another
    left behind.

    ``metric`` names what :meth:`evaluate` reports: ``"mse"`` (lower is better; the loss itself) or
    ``"return"`` (higher is better; the loss is the negative return). ``on_policy`` says whether the
    data are θ's own rollouts (RL): a step outdates them, so the follower's losses at θ_{t+1} need
    a fresh :meth:`collect`; otherwise (regression, system identification) they are scored on the
    step's own data, as the follower update of paper Algorithms 1 and 2 does
    (L(D^Q_τ; θ_{t+1}) on the same D^S, D^Q).

    Examples:
        >>> import torch
        >>> from armeta_rl.collectors import SinusoidCollector
        >>> from armeta_rl.learners import Leader, MAMLLeader, make_mlp
        >>> from armeta_rl.learners.maml import MamlOptions
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> _ = torch.manual_seed(0)
        >>> leader = MAMLLeader(make_mlp(1, 1, hidden=[16]), SinusoidCollector(20, 50),
        ...                     MamlOptions(outer_lr=0.01))
        >>> isinstance(leader, Leader)
        True
        >>> space = TaskSpace(["amplitude", "phase"], low=[0.1, 0.0], high=[5.0, 3.1416])
        >>> data = leader.collect(BoxUniform(space).sample(4))  # the loop's three verbs
        >>> per_task, _ = leader.step(data, weights=lambda losses: torch.full_like(losses, 0.25))
        >>> per_task["loss"]  # each task's adapted loss at θ_t
        tensor([ 9.6684,  4.6846, 12.3939,  5.7636])
        >>> leader.evaluate(data)  # the same tasks' at θ_{t+1}: the step lowered every one
        tensor([ 9.4611,  4.4347, 12.1239,  5.5539])
    """

    metric: str
    on_policy: bool
    collector: TaskCollector

    def collect(self, tasks: TensorDict, collector: TaskCollector | None = None,
                create_graph: bool = False) -> Any:
        """The data of ``tasks`` ``[K]`` at the current θ, from ``collector`` (e.g. the larger
        evaluation collector) or the leader's own; the loop passes them on unchanged.
        ``create_graph``: the data will be differentiated for :meth:`step`'s meta-gradient, so
        any part computed from θ (MAML-TRPO's adapted policies) keeps its graph."""
        ...

    def step(self, data: Any, weights: TaskWeights) -> tuple[TensorDict, dict[str, float]]:
        """One leader update on the data of :meth:`collect`: adapt, score, and step θ on
        Σ_k w_k L_k with ``w = weights(L.detach())``.

        Returns a TensorDict ``[K]`` with the detached per-task ``"loss"`` (before the update) and
        any other per-task metrics worth logging (e.g. ``"return_pre"``, ``"return_post"``), and a
        dict of the step's scalar diagnostics (e.g. TRPO's accepted KL; empty if none).
        """
        ...

    def evaluate(self, data: Any) -> Tensor:
        """Per-task loss after adaptation ``[K]`` of ``data`` at the current θ, without updating
        θ."""
        ...

    def evaluate_before(self, data: Any) -> Tensor | None:
        """Per-task loss before adaptation ``[K]`` of the same ``data``: θ's own, on the same
        tasks and random streams as :meth:`evaluate`, so that their difference is the paired
        adaptation gain (:func:`~armeta_rl.trainers.evaluation.adaptation_gain`); ``None`` for
        a leader that reports none."""
        ...

    def adapted_episodes(self, data: Any) -> TensorDict | None:
        """The adapted learner's episodes in ``data`` ``[K, E, T]`` (meta-RL), whose returns
        :meth:`evaluate` scores, so that an evaluation can split them into what the goal and
        what the rest of the reward gives (:func:`~armeta_rl.trainers.evaluation.gap_closed`);
        ``None`` for a leader without episodes."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """Parameters and optimizer state, for checkpoints."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned."""
        ...


class OneNetworkLeader:
    """What leaders made of one network and one optimizer share (MAML, CNP): the weighted
    meta-update θ ← opt(∇_θ Σ_k w_k L_k) (paper Eq. (15) with task weights) and their
    checkpoint state."""

    model: nn.Module
    optimizer: torch.optim.Optimizer
    collector: TaskCollector
    on_policy = False

    def collect(self, tasks: TensorDict, collector: TaskCollector | None = None,
                create_graph: bool = False) -> TensorDict:
        """Support and query data ``[K]`` of ``tasks`` from ``collector`` or the leader's own; they
        do not depend on θ (so ``create_graph`` changes nothing)."""
        return (self.collector if collector is None else collector).collect(tasks)

    def evaluate_before(self, data: TensorDict) -> None:
        """No loss before adaptation is reported for regression and system identification (the
        adaptation gain is a meta-RL metric)."""
        return None

    def adapted_episodes(self, data: TensorDict) -> None:
        """No episodes in regression and system identification."""
        return None

    def descend(self, losses: Tensor, weights: TaskWeights) -> None:
        """One optimizer step on Σ_k w_k L_k with ``w = weights(L.detach())``."""
        task_weights = weights(losses.detach())
        self.optimizer.zero_grad(set_to_none=True)
        weighted_sum(task_weights, losses).backward()
        self.optimizer.step()

    def state_dict(self) -> dict[str, Any]:
        """Network parameters and optimizer state."""
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned."""
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])


def sizes(collector: TaskCollector) -> tuple[int, int]:
    """The leader's input and output sizes, as the collector defines them (``in_features`` and
    ``out_features``: x and y, or the env's observation and action)."""
    return int(collector.in_features), int(collector.out_features)
