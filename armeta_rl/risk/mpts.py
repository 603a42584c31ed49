"""MPTS, the ``mpts`` principle: model predictive task sampling with a UCB-like acquisition (Wang
et al. 2025, arXiv 2501.11039; its pipeline restated as Eqs. (6)–(7) of the PDTS paper).

Each iteration draws a pseudo-batch of B̂ candidates from p0, estimates for each the mean m(ℓ_i)
and standard deviation σ(ℓ_i) of its predicted adaptation loss from several stochastic forward
passes z_t ~ q_φ(z_t | H_t) of the risk model (Eq. (6b)), and trains on the B candidates with the
largest

    a(τ_i) = γ0·m(ℓ_i) + γ1·σ(ℓ_i)                                        (Eq. (7))

(the subset maximizing A_U(T^B) = Σ_i a(τ_i) is the top B, Eq. (6c)): hard tasks and tasks the
model is unsure about first, optimism in the face of uncertainty. The MPTS repository's meta-RL
code mixes in random candidates (half the batch) against the selection's concentration; the
``random_fraction`` option does so. The risk model and its streaming training are
:mod:`armeta_rl.risk.predictive`'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from armeta_rl.fields import at_least, inside, register
from armeta_rl.risk.predictive import (
    PredictiveOptions,
    PredictivePrinciple,
    RiskPredictiveModel,
    candidate_ratio,
    check_scores,
    sample_latent,
)
from armeta_rl.tasks.distributions import TaskDistribution


@register("risk.mpts")
@dataclass(frozen=True)
class MptsOptions(PredictiveOptions):
    """``risk.mpts``: the keys of :class:`MPTSPrinciple`, their types, ranges and defaults (the
    shared ones: :class:`~armeta_rl.risk.predictive.PredictiveOptions`).

    Attributes:
        candidate_ratio: B̂ / B; the MPTS sinusoid code's 2 (32 candidates for 16 tasks); its
            meta-RL code uses 1.5.
        gamma_mean: γ0, the weight of the predicted mean loss m(ℓ).
        gamma_std: γ1, the weight of its standard deviation σ(ℓ); the sinusoid code's 3, the
            meta-RL code's 5.
        score_samples: the z samples behind m(ℓ) and σ(ℓ) (sinusoid 20, meta-RL 50).
        random_fraction: the fraction of the batch drawn at random from the candidates instead of
            by score (the meta-RL code's mixing: 0.5; its sinusoid code: none).
    """

    candidate_ratio: float = candidate_ratio(default=2.0)
    gamma_mean: float = at_least(0, default=1.0)
    gamma_std: float = at_least(0, default=3.0)
    score_samples: int = at_least(2, default=20)
    random_fraction: float = inside(0, 1, "[)", default=0.0)


@torch.no_grad()
def predictive_moments(
    model: RiskPredictiveModel, unit: Tensor, loc: Tensor, scale: Tensor, samples: int
) -> tuple[Tensor, Tensor]:
    """m(ℓ_i) and σ(ℓ_i) ``[N]`` of Eqs. (6b)–(7): the mean and standard deviation of the predicted
    loss of ``N`` candidates ``[N, d]`` (unit box) over ``samples`` forward passes with
    z_t ~ q_φ(z_t | H_t) = N(loc, diag scale²), all in one batched pass."""
    predictions = model.predict(unit, sample_latent(loc, scale, samples))
    return predictions.mean(0), predictions.std(0)


def ucb_scores(mean: Tensor, std: Tensor, gamma_mean: float, gamma_std: float) -> Tensor:
    """The acquisition a(τ_i) = γ0·m(ℓ_i) + γ1·σ(ℓ_i) of Eq. (7), per candidate."""
    return gamma_mean * mean + gamma_std * std


def top_b(scores: Tensor, b: int) -> Tensor:
    """Eq. (6c) for A_U(T^B) = Σ_i a(τ_i): the subset of size ``b`` with the largest sum is the
    ``b`` largest scores; their indices, best first."""
    return torch.topk(scores, b).indices


def mixed_selection(scores: Tensor, b: int, random_fraction: float) -> Tensor:
    """``b`` indices: the top ``b − floor(random_fraction · b)`` scores (:func:`top_b`), then the
    first candidates in draw order not already picked (p0 draws: a uniformly random subset of
    the rest), as the MPTS meta-RL code mixes random tasks into the batch."""
    keep = b - math.floor(round(random_fraction * b, 9))
    chosen = top_b(scores, keep)
    if keep == b:
        return chosen
    rest = torch.ones_like(scores, dtype=torch.bool).index_fill(0, chosen, False)
    return torch.cat([chosen, rest.nonzero().squeeze(-1)[: b - keep]])


class MPTSPrinciple(PredictivePrinciple):
    """MPTS-MAML / MPTS-CNP's task source: the top B of a pseudo-batch of p0 by the UCB score of
    Eq. (7) under the risk model (:class:`~armeta_rl.risk.predictive.PredictivePrinciple`).

    Args:
        initial: p0.
        options: the keys of ``risk.mpts`` (:class:`MptsOptions`).

    Examples:
        >>> import torch
        >>> from armeta_rl.risk import MPTSPrinciple
        >>> from armeta_rl.risk.mpts import MptsOptions
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> _ = torch.manual_seed(0)
        >>> p0 = BoxUniform(TaskSpace(["x"], low=[0.0], high=[1.0]))
        >>> principle = MPTSPrinciple(p0, MptsOptions(candidate_ratio=4.0, lr=0.01, steps=5))
        >>> for _ in range(20):  # 8 tasks of 32 candidates, 20 times; the learner's loss is x
        ...     tasks = principle.propose(8)
        ...     stats = principle.update(tasks, losses=tasks["params"][:, 0])
        >>> round(stats["risk/pcc"], 2)  # the risk model ranks the last batch's losses right
        1.0
        >>> grid = torch.linspace(0.0, 1.0, 11)[:, None]  # 0, 0.1, ..., 1
        >>> grid[principle.select(grid, 3)].flatten()  # the 3 of largest a = m + 3σ, Eq. (7)
        tensor([1.0000, 0.9000, 0.8000])
    """

    def __init__(self, initial: TaskDistribution, options: MptsOptions = MptsOptions()) -> None:
        super().__init__(initial, options)
        self.gamma_mean, self.gamma_std = float(options.gamma_mean), float(options.gamma_std)
        self.score_samples, self.random_fraction = options.score_samples, options.random_fraction

    def scores(self, params: Tensor) -> Tensor:
        """a(τ_i) of Eq. (7) for candidates ``params [N, d]`` under the stored posterior."""
        mean, std = predictive_moments(self.model, self.unit(params), self.posterior_loc,
                                       self.posterior_scale, self.score_samples)
        return ucb_scores(mean, std, self.gamma_mean, self.gamma_std)

    def select(self, params: Tensor, n: int) -> Tensor:
        """The top ``n`` candidates by :meth:`scores` (with the random share, if any).

        Raises:
            TrainingDiverged: a non-finite score.
        """
        scores = check_scores(self.scores(params), self.section)
        return mixed_selection(scores, n, self.random_fraction)
