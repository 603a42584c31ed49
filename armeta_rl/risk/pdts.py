"""PDTS, the ``pdts`` principle: posterior and diversity synergized task sampling (Qu et al.,
ICML 2025, "Fast and Robust: Task Sampling with Posterior and Diversity Synergies for Adaptive
Decision-Makers in Randomized Environments"; Algorithm 1 and Eq. (12)).

It keeps MPTS's risk model (:mod:`armeta_rl.risk.predictive`) and changes the acquisition:

    z_t ~ q_φ(z_t | H_t)                               one forward pass   (Eq. (12a))
    ℓ̂_i ~ p_ψ(ℓ | τ̂_i, z_t)   for every candidate                        (Eq. (12b))
    T^B = argmax_{|T^B| = B} Σ_{i∈T^B} ℓ̂_i + γ·S(T^B)                    (Eq. (12c))

Posterior sampling (one z for the whole pseudo-batch, Thompson-style) replaces the UCB score, and
S, the diversity of the subset's identifiers, counters the concentration of the top-B rule around
the predicted worst task (the paper's Proposition 3.3), which lets B̂ grow to 64·B. S is the mean
pairwise Euclidean distance 2/(B(B−1))·Σ_{i<j} ‖τ_i − τ_j‖ (the normalization of the authors'
sinusoid code; the paper's Eq. (11) names pairwise distances). The subset problem is NP-hard;
it is solved with the greedy algorithm for max-sum diversification of Borodin et al. (2017):
add the candidate u maximizing ½·ℓ̂_u + λ·Σ_{v∈S} d(u, v), with λ = 2γ/(B(B−1)) the weight of
Σ_{i<j} d in the objective, a 2-approximation when the ℓ̂ are non-negative.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from armeta_rl.fields import at_least, one_of, register
from armeta_rl.risk.predictive import (
    PredictiveOptions,
    PredictivePrinciple,
    RiskPredictiveModel,
    candidate_ratio,
    check_scores,
    sample_latent,
)
from armeta_rl.tasks.distributions import TaskDistribution

DISTANCES = ("identifier", "unit")


@register("risk.pdts")
@dataclass(frozen=True)
class PdtsOptions(PredictiveOptions):
    """``risk.pdts``: the keys of :class:`PDTSPrinciple`, their types, ranges and defaults (the
    shared ones: :class:`~armeta_rl.risk.predictive.PredictiveOptions`).

    Attributes:
        candidate_ratio: B̂ / B; the paper's sinusoid setting 32 (512 candidates for 16 tasks);
            64 is its default elsewhere.
        diversity: γ, the weight of the diversity S in Eq. (12c) (the paper's default 1; 0 is
            posterior sampling with the top-B rule).
        distance: where distances are measured: between the identifiers themselves
            (``identifier``, the papers') or their images in the unit box (``unit``: every
            identifier weighs the same whatever its range).
    """

    candidate_ratio: float = candidate_ratio(default=32.0)
    diversity: float = at_least(0, default=1.0)
    distance: str = one_of(*DISTANCES, default="identifier")


@torch.no_grad()
def posterior_sample_risks(
    model: RiskPredictiveModel, unit: Tensor, loc: Tensor, scale: Tensor
) -> Tensor:
    """ℓ̂_i ``[N]`` of Eqs. (12a)–(12b): one z_t ~ q_φ(z_t | H_t) = N(loc, diag scale²) shared by
    all ``N`` candidates ``[N, d]`` (unit box), and each candidate's predicted loss under it."""
    return model.predict(unit, sample_latent(loc, scale, 1))[0]


def mean_pairwise_distance(points: Tensor) -> Tensor:
    """S(T^B) = 2/(B(B−1))·Σ_{i<j} ‖τ_i − τ_j‖ of ``points [B, d]`` (0 for one point): the
    diversity of Eq. (11)."""
    b = len(points)
    if b < 2:
        return points.new_zeros(())
    return torch.pdist(points).sum() * 2 / (b * (b - 1))


def greedy_diverse_subset(risks: Tensor, points: Tensor, b: int, diversity: float) -> Tensor:
    """Indices ``[b]`` of an approximate maximizer of Eq. (12c) over the candidates (risks
    ``[N]``, points ``[N, d]``), in the order picked: Borodin et al.'s greedy, which adds the
    candidate with the largest ½·ℓ̂_u + λ·Σ_{v∈S} d(u, v), λ = 2γ/(b(b−1)). Each pick is one
    batched pass over all candidates (their distance to the last pick is added to a running
    sum); ties go to the earlier candidate."""
    weight = 2.0 * diversity / (b * (b - 1)) if b > 1 else 0.0
    half = 0.5 * risks
    distance_sum = torch.zeros_like(risks)
    taken = torch.zeros_like(risks, dtype=torch.bool)
    chosen = torch.empty(b, dtype=torch.long, device=risks.device)
    for step in range(b):
        gains = torch.where(taken, -torch.inf, half + weight * distance_sum)
        pick = torch.argmax(gains)
        chosen[step] = pick
        taken[pick] = True
        distance_sum += (points - points[pick]).norm(dim=-1).to(distance_sum)
    return chosen


class PDTSPrinciple(PredictivePrinciple):
    """PDTS-MAML / PDTS-CNP's task source: a posterior sample of the risk model's predictions over
    a pseudo-batch of p0, and the greedy diverse subset of Eq. (12c)
    (:class:`~armeta_rl.risk.predictive.PredictivePrinciple`).

    Args:
        initial: p0.
        options: the keys of ``risk.pdts`` (:class:`PdtsOptions`).

    Examples:
        >>> import torch
        >>> from armeta_rl.risk import PDTSPrinciple
        >>> from armeta_rl.risk.pdts import PdtsOptions
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> _ = torch.manual_seed(0)
        >>> p0 = BoxUniform(TaskSpace(["x"], low=[0.0], high=[1.0]))
        >>> principle = PDTSPrinciple(p0, PdtsOptions(candidate_ratio=4.0, lr=0.01, steps=5))
        >>> for _ in range(20):  # 8 tasks of 32 candidates, 20 times; the learner's loss is x
        ...     tasks = principle.propose(8)
        ...     stats = principle.update(tasks, losses=tasks["params"][:, 0])
        >>> round(stats["risk/pcc"], 2)  # the risk model ranks the last batch's losses right
        1.0
        >>> grid = torch.linspace(0.0, 1.0, 11)[:, None]  # 0, 0.1, ..., 1
        >>> grid[principle.select(grid, 3)].flatten()  # the 2 hardest, then the farthest from them
        tensor([1.0000, 0.9000, 0.0000])
    """

    def __init__(self, initial: TaskDistribution, options: PdtsOptions = PdtsOptions()) -> None:
        super().__init__(initial, options)
        self.diversity, self.distance = float(options.diversity), options.distance

    def select(self, params: Tensor, n: int) -> Tensor:
        """``n`` candidates by :func:`greedy_diverse_subset` on the posterior sample of
        :func:`posterior_sample_risks`, distances between the identifiers or their unit-box
        images (``distance``).

        Raises:
            TrainingDiverged: a non-finite predicted risk.
        """
        unit = self.unit(params)
        risks = check_scores(
            posterior_sample_risks(self.model, unit, self.posterior_loc, self.posterior_scale),
            self.section,
        )
        points = params.to(risks) if self.distance == "identifier" else unit
        return greedy_diverse_subset(risks, points, n, self.diversity)
