"""The risk-principle protocol: where tasks come from and how losses become the objective."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from tensordict import TensorDict
from torch import Tensor


@runtime_checkable
class RiskPrinciple(Protocol):
    """ERM, CVaR (DR), worst-case (TR), group-DRO and the flow adversary (AR).

    ``update_every`` is the follower's update interval ``u`` in meta-iterations; ``0`` means the
    principle never needs :meth:`update` (plain ERM), so the trainer skips the evaluation it costs.
    """

    update_every: int

    def propose(self, n: int) -> TensorDict:
        """``n`` tasks ``{"params": [n, d], "log_prob": [n]}`` for the next leader step."""
        ...

    def weights(self, losses: Tensor) -> Tensor:
        """Non-negative task weights ``[K]`` summing to one, from detached losses ``[K]``."""
        ...

    def update(self, tasks: TensorDict, losses: Tensor) -> dict[str, float]:
        """Follower step on the losses of ``tasks`` at θ_{t+1}; returns scalars to log."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """Follower parameters and optimizer state, for checkpoints."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned."""
        ...
