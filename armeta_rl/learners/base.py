"""The leader protocol (docs/architecture.md): MAML, CNP and MAML-TRPO all implement it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import torch
from tensordict import TensorDict
from torch import Tensor, nn

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
        A leader whose data do not depend on θ (regression, system identification) scores the
        tasks of its last :meth:`step` on that step's data, as the follower update of paper
        Algorithms 1 and 2 does (L(D^Q_τ; θ_{t+1}) on the same D^S, D^Q).
        """
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
    collector: Collector
    _stepped: tuple[TensorDict, TensorDict] | None = None

    def step_data(self, tasks: TensorDict) -> TensorDict:
        """Collect the data of a leader step on ``tasks`` and keep them for :meth:`task_data`."""
        data = self.collector.collect(tasks)
        self._stepped = (tasks, data)
        return data

    def task_data(self, tasks: TensorDict, collector: Collector | None = None) -> TensorDict:
        """Data to score ``tasks`` on: from ``collector`` if given; else the data of the last
        :meth:`step_data` if ``tasks`` is the very TensorDict it was called with (the follower
        scores the leader's D^S, D^Q at θ_{t+1}, paper Algorithms 1 and 2, and no second
        collection is paid); else a fresh collection by the leader's collector."""
        if collector is None and self._stepped is not None and self._stepped[0] is tasks:
            return self._stepped[1]
        return (collector or self.collector).collect(tasks)

    def descend(self, losses: Tensor, weights: TaskWeights) -> None:
        """One optimizer step on Σ_k w_k L_k with ``w = weights(L.detach())``."""
        task_weights = weights(losses.detach())
        self.optimizer.zero_grad(set_to_none=True)
        (task_weights * losses).sum().backward()
        self.optimizer.step()

    def state_dict(self) -> dict[str, Any]:
        """Network parameters and optimizer state."""
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned."""
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
