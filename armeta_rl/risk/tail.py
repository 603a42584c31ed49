"""Tail-risk minimization, the ``dr`` principle (DR-MAML, Wang et al. 2023).

Paper Eq. (2) (and Eq. (20) in its appendix "Robust Fast Adaptation Strategies in the Task
Space"): the leader minimizes E_{p_α(τ;θ)}[L(D^Q_τ, D^S_τ; θ)], the expected loss over the
normalized tail of the task-loss distribution, i.e. CVaR_α of the task loss under the fixed p0.
In a batch this is the importance-weighted form (Eq. (21)): the α-quantile (VaR) of
the batch losses is estimated and the tasks at or above it get equal weight, the others zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict
from torch import Tensor, nn

from armeta_rl.fields import Section, inside, key, register
from armeta_rl.tasks.distributions import TaskDistribution


def tail_size(batch_size: int, alpha: float) -> int:
    """Number of tasks kept in the worst (1 − α) tail of a batch: ``ceil((1 − α)·K)``.

    The ceiling keeps at least one task for every α in (0, 1); with α = 0.5 and an even ``K`` it
    is exactly ``K / 2``.
    """
    return exact_ceil((1.0 - alpha) * batch_size)


def exact_ceil(value: float) -> int:
    """The ceiling of ``value`` rounded to 9 decimals first, so that floating-point noise
    (``0.3 * 10 = 3.0000000000000004``) does not add one."""
    return math.ceil(round(value, 9))


def value_at_risk(losses: Tensor, alpha: float) -> Tensor:
    """Empirical α-quantile (VaR_α) of a batch of losses ``[K]``: the smallest loss kept in the
    tail of :func:`tail_size` tasks."""
    keep = tail_size(losses.numel(), alpha)
    return torch.topk(losses.detach(), keep).values[-1]


def tail_weights(losses: Tensor, alpha: float) -> Tensor:
    """The importance weights ω(τ_k; θ) of paper Eq. (21) for a batch of losses ``[K]``: ``1 / m``
    on the ``m = ceil((1 − α)·K)`` largest losses, 0 elsewhere, so that Σ_k ω_k L_k is the
    batch's empirical CVaR_α. Ties at the VaR are broken by :func:`torch.topk`, so exactly ``m``
    tasks are kept."""
    keep = tail_size(losses.numel(), alpha)
    worst = torch.topk(losses.detach(), keep).indices
    weights = torch.zeros_like(losses)
    return weights.index_fill(0, worst, 1.0 / keep)


def tail_risk(losses: Tensor, alpha: float) -> Tensor:
    """Σ_k ω_k L_k with the weights of :func:`tail_weights`: the estimate of paper Eq. (21) of
    the tail risk of Eq. (2), the value the DR leader minimizes."""
    return (tail_weights(losses, alpha) * losses).sum()


@register("risk.dr")
@dataclass(frozen=True)
class DrOptions(Section):
    """``risk.dr``: the keys of :class:`TailRiskPrinciple`, their types, ranges and defaults.

    Attributes:
        alpha: confidence level α ∈ (0, 1); the leader trains on the worst ``ceil((1 − α)·K)``
            tasks of each batch of ``K`` (see :func:`tail_size`).
        oversample: when ``True``, :meth:`TailRiskPrinciple.propose` draws
            ``ceil(n / (1 − α))`` candidates instead of ``n``, so that the tail the leader trains
            on holds about ``n`` tasks, as many as an ERM step uses. The trainer then passes the
            whole returned batch to the leader (its size is ``tasks.batch_size[0]``, not ``n``);
            the weights zero the tasks outside the tail. When ``False`` the tail of a meta-batch
            of ``n`` tasks is about ``(1 − α)·n``.
    """

    alpha: float = inside(0, 1, default=0.5)  # as in the paper
    oversample: bool = key(default=False)  # propose ceil(K / (1 − α)): the tail keeps ≈ K tasks


class TailRiskPrinciple(nn.Module):
    """CVaR_α (tail-risk) weighting of tasks drawn from the fixed initial distribution p0
    (DR, Wang et al. 2023: the update is on the worst (1 − α) tail of the batch).

    Args:
        initial: p0, where every task comes from.
        options: the keys of ``risk.dr`` (:class:`DrOptions`): α and whether to oversample.

    It has no follower; its :meth:`update` reports VaR_α and CVaR_α of each step's own losses
    (``update_every = 1`` on the step's losses, ``needs_next_losses = False``: no extra
    evaluation).

    Examples:
        >>> import torch
        >>> from armeta_rl.risk import TailRiskPrinciple
        >>> from armeta_rl.risk.tail import DrOptions
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> p0 = BoxUniform(TaskSpace(["x"], low=[0.0], high=[1.0]))
        >>> principle = TailRiskPrinciple(p0, DrOptions(alpha=0.5))
        >>> tasks, losses = principle.propose(4), torch.tensor([1.0, 2.0, 3.0, 4.0])
        >>> principle.weights(losses, tasks)  # the worst half of the batch
        tensor([0.0000, 0.0000, 0.5000, 0.5000])
        >>> principle.update(tasks, losses)
        {'risk/var': 3.0, 'risk/cvar': 3.5}
    """

    update_every = 1
    needs_next_losses = False
    label = "loss"

    def __init__(self, initial: TaskDistribution, options: DrOptions = DrOptions()) -> None:
        super().__init__()
        self.initial = initial
        self.alpha = float(options.alpha)
        self.oversample = options.oversample

    def propose(self, n: int) -> TensorDict:
        """Candidate tasks from p0: ``n``, or ``ceil(n / (1 − α))`` when oversampling."""
        count = exact_ceil(n / (1.0 - self.alpha)) if self.oversample else n
        return self.initial.sample(count)

    def weights(self, losses: Tensor, tasks: TensorDict | None = None) -> Tensor:
        """The weights ω of paper Eq. (21) (:func:`tail_weights`), whatever the tasks."""
        return tail_weights(losses, self.alpha)

    def update(self, tasks: TensorDict, losses: Tensor) -> dict[str, float]:
        """No follower to update; reports VaR_α and CVaR_α of the step's ``losses`` (the loss the
        leader minimized, :func:`tail_risk`) for logging."""
        losses = losses.detach()
        return {
            "risk/var": float(value_at_risk(losses, self.alpha)),
            "risk/cvar": float(tail_risk(losses, self.alpha)),
        }
