"""The leader protocol (ARCHITECTURE.md): MAML, CNP and MAML-TRPO all implement it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

from tensordict import TensorDict
from torch import Tensor

from armeta_rl.collectors.base import Collector

TaskWeights = Callable[[Tensor], Tensor]
"""Maps detached per-task losses ``[K]`` to non-negative weights ``[K]`` that sum to one."""


@runtime_checkable
class Leader(Protocol):
    """The meta-learner θ: collects data for the tasks, adapts, scores and updates itself.

    ``metric`` names what :meth:`evaluate` reports: ``"mse"`` (lower is better; the loss itself) or
    ``"return"`` (higher is better; the loss is the negative return).
    """

    metric: str
    collector: Collector

    def step(self, tasks: TensorDict, weights: TaskWeights) -> TensorDict:
        """One leader update on ``tasks`` ``[K]``: collect, adapt, score, and step θ on
        Σ_k w_k L_k with ``w = weights(L.detach())``.

        Returns a TensorDict ``[K]`` with the detached per-task ``"loss"`` (before the update) and
        any other per-task metrics worth logging (e.g. ``"return_pre"``, ``"return_post"``).
        """
        ...

    def evaluate(self, tasks: TensorDict, collector: Collector | None = None) -> Tensor:
        """Per-task loss after adaptation ``[K]`` at the current θ, without updating θ.

        Data come from ``collector`` (e.g. the larger evaluation collector) or the leader's own.
        """
        ...

    def state_dict(self) -> dict[str, Any]:
        """Parameters and optimizer state, for checkpoints."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned."""
        ...
