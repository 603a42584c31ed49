"""The risk-principle protocol: where tasks come from and how losses become the objective."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from tensordict import TensorDict
from torch import Tensor


@runtime_checkable
class RiskPrinciple(Protocol):
    """ERM, CVaR (DR), worst-case (TR), group-DRO and the flow adversary (AR).

    ``update_every`` is the update interval ``u`` in meta-iterations; ``0`` means the principle
    never needs :meth:`update` (plain ERM). ``needs_next_losses`` says which losses :meth:`update`
    reads: ``True`` for a follower of the game, the losses of the step's tasks at θ_{t+1} (the
    trainer evaluates the leader again for them); ``False`` for the step's own losses at θ_t,
    which cost nothing more (DR reports their tail statistics). ``label`` names the per-task
    output of the leader's step that :meth:`update` reads: ``"loss"``, the task loss, for every
    principle but MPTS's and PDTS's meta-RL option ``label=last_step``
    (``"last_step_loss"``, :meth:`~armeta_rl.learners.maml_trpo.MAMLTRPOLeader.scores`).

    Examples:
        >>> import torch
        >>> from armeta_rl.risk import ERMPrinciple, RiskPrinciple
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> principle = ERMPrinciple(BoxUniform(TaskSpace(["x"], low=[0.0], high=[1.0])))
        >>> isinstance(principle, RiskPrinciple)
        True
        >>> tasks = principle.propose(4)  # where tasks come from
        >>> principle.weights(torch.tensor([1.0, 2.0, 3.0, 4.0]), tasks)  # how losses weigh
        tensor([0.2500, 0.2500, 0.2500, 0.2500])
    """

    update_every: int
    needs_next_losses: bool
    label: str

    def propose(self, n: int) -> TensorDict:
        """``n`` tasks ``{"params": [n, d], "log_prob": [n]}`` for the next leader step."""
        ...

    def weights(self, losses: Tensor, tasks: TensorDict) -> Tensor:
        """Non-negative task weights ``[K]`` summing to one, from detached losses ``[K]`` of
        ``tasks`` ``[K]``: a pure function of both (the trainer binds ``tasks`` and hands the
        leader ``losses ↦ weights(losses, tasks)``)."""
        ...

    def update(self, tasks: TensorDict, losses: Tensor) -> dict[str, float]:
        """Update on the losses of ``tasks`` (see ``needs_next_losses``); returns scalars to
        log."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """Parameters and optimizer state, for checkpoints."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned."""
        ...
