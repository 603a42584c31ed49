"""Task-group principles: worst-case ``tr`` (TR-MAML) and group DRO ``dro`` (DRO-MAML).

Paper, table "A Summary of Used Methods" and appendix "Robust Fast Adaptation Strategies in the
Task Space", Eq. (19): min_θ max_{g∈G} E_{p_g(τ)}[L(D^Q_τ, D^S_τ; θ)]. The groups G are
the cells of a regular grid over the identifier box (``groups_per_axis`` cells per identifier, so
``groups_per_axis ** d`` groups). The inner max over groups is relaxed to a max over group weights q
on the probability simplex, min_θ max_{q∈Δ} Σ_g q_g L_g(θ), and q follows the group losses:

* ``tr`` (Collins et al. 2020, TR-MAML): projected gradient ascent, q ← Π_Δ(q + η·L̄).
* ``dro`` (Sagawa et al. 2020, group DRO): exponentiated gradient, q ← q·exp(η·L̄) / Z.

L̄_g is the mean loss of the batch tasks in group g. A group with no task in the batch has no loss
estimate: its entry of L̄ is 0, so its weight is moved only by the normalization (as in Sagawa et
al.'s reference code). Tasks always come from the fixed p0 (the table's "Task Distribution: Fixed");
the groups only decide how the leader weighs them.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict
from torch import Tensor, nn

from armeta_rl.fields import Section, above, at_least, register
from armeta_rl.tasks.distributions import TaskDistribution
from armeta_rl.tasks.protocol import TASK_KEY


def project_to_simplex(v: Tensor) -> Tensor:
    """Euclidean projection of ``v [G]`` onto the probability simplex {q ≥ 0, Σ q = 1}.

    Sort-based algorithm of Duchi et al. (2008), "Efficient projections onto the l1-ball":
    q = max(v − τ, 0) with the threshold τ = (Σ_{i≤ρ} u_i − 1) / ρ, where u is v sorted in
    decreasing order and ρ the largest index with u_ρ − (Σ_{i≤ρ} u_i − 1) / ρ > 0.
    """
    u = torch.sort(v, descending=True).values
    cumulative = u.cumsum(0) - 1.0
    index = torch.arange(1, v.numel() + 1, dtype=v.dtype, device=v.device)
    support = (u - cumulative / index) > 0
    rho = int(support.nonzero().max()) + 1
    threshold = cumulative[rho - 1] / rho
    return (v - threshold).clamp_min(0.0)


@dataclass(frozen=True)
class _GroupOptions(Section):
    """The keys a group principle's section shares; each principle's options give ``step_size``
    its own default.

    Attributes:
        groups_per_axis: grid cells per identifier; ``groups_per_axis ** d`` groups.
        step_size: η of the step of the group weights q.
    """

    groups_per_axis: int = at_least(1, default=3)  # the box is split into a grid of task groups
    step_size: float = above(0)


@register("risk.tr")
@dataclass(frozen=True)
class TrOptions(_GroupOptions):
    """``risk.tr``: the keys of :class:`WorstCasePrinciple`, their types, ranges and defaults."""

    # chosen on a validation seed and validation tasks (docs/notes/history.md)
    step_size: float = above(0, default=1.0e-5)


@register("risk.dro")
@dataclass(frozen=True)
class DroOptions(_GroupOptions):
    """``risk.dro``: the keys of :class:`GroupDROPrinciple`, their types, ranges and defaults."""

    # chosen as tr's (docs/notes/history.md)
    step_size: float = above(0, default=1.0e-4)


class _GroupPrinciple(nn.Module):
    """Group weights q over a grid of the identifier box; subclasses define the q step."""

    update_every = 1
    needs_next_losses = True
    label = "loss"

    def __init__(self, initial: TaskDistribution, options: _GroupOptions) -> None:
        super().__init__()
        self.initial = initial
        self.groups_per_axis = options.groups_per_axis
        self.step_size = float(options.step_size)
        self.num_groups = self.groups_per_axis ** initial.space.dim
        self.register_buffer("q", torch.full((self.num_groups,), 1.0 / self.num_groups,
                                             dtype=torch.float64))

    def group_of(self, params: Tensor) -> Tensor:
        """Group index ``[n]`` of each task: its grid cell, numbered row-major over the axes.

        A point on an inner cell boundary belongs to the upper cell; the box's upper edge belongs
        to the last cell.
        """
        unit = self.initial.space.to_unit(params.to(torch.float64))
        cell = (unit * self.groups_per_axis).floor().long().clamp(0, self.groups_per_axis - 1)
        axes = torch.arange(cell.shape[-1] - 1, -1, -1, device=cell.device)
        strides = self.groups_per_axis ** axes
        return (cell * strides).sum(-1)

    def propose(self, n: int) -> TensorDict:
        """``n`` tasks from p0."""
        return self.initial.sample(n)

    def weights(self, losses: Tensor, tasks: TensorDict) -> Tensor:
        """w_k = q_{g(k)} / n_{g(k)} / Σ_{g present} q_g for the tasks of a batch (the group
        objective of paper Eq. (19) with the max over groups relaxed to the weights q).

        n_g is the number of batch tasks in group g, so Σ_k w_k L_k = Σ_g q_g L̄_g / Σ_{g present}
        q_g: the q-weighted group risk, renormalized over the groups present in the batch. If every
        present group has q_g = 0 (``tr`` can sit on a vertex whose group the batch missed), the
        present groups share the weight equally, the limit of q + ε·1 as ε → 0. The groups are
        those of ``tasks``, the batch the losses belong to.
        """
        groups = self.group_of(tasks[TASK_KEY])
        if groups.numel() != losses.numel():
            raise ValueError(f"{losses.numel()} losses for a batch of {groups.numel()} tasks")
        groups = groups.to(losses.device)
        q = self.q.to(losses.device)
        counts = torch.bincount(groups, minlength=self.num_groups).to(q)
        present_q = q * (counts > 0)
        if not present_q.sum() > 0:
            present_q = (counts > 0).to(q)
        return (present_q[groups] / counts[groups] / present_q.sum()).to(losses.dtype)

    def group_losses(self, tasks: TensorDict, losses: Tensor) -> tuple[Tensor, Tensor]:
        """Mean loss per group ``[G]`` (0 where absent) and the mask of groups present ``[G]``."""
        groups = self.group_of(tasks[TASK_KEY]).to(self.q.device)
        losses = losses.detach().to(self.q)
        counts = torch.bincount(groups, minlength=self.num_groups).to(self.q)
        sums = torch.zeros_like(self.q).index_add(0, groups, losses)
        return sums / counts.clamp_min(1.0), counts > 0

    def update(self, tasks: TensorDict, losses: Tensor) -> dict[str, float]:
        """One ascent step of q on the per-group mean losses at θ_{t+1}."""
        mean_losses, present = self.group_losses(tasks, losses)
        self.q.copy_(self._ascent_step(self.q, mean_losses))
        return {
            "risk/max_group_weight": float(self.q.max()),
            "risk/worst_group_loss": float(mean_losses[present].max()),
        }

    def _ascent_step(self, q: Tensor, group_losses: Tensor) -> Tensor:
        raise NotImplementedError


class WorstCasePrinciple(_GroupPrinciple):
    """``tr``: TR-MAML (Collins et al. 2020), min_θ max_{q∈Δ} Σ_g q_g L_g(θ): the worst case of
    paper Eq. (3), taken over the grid's groups.

    q takes a projected gradient-ascent step on the group losses every meta-iteration:
    q ← Π_Δ(q + η·L̄) (:func:`project_to_simplex`). Linear in q, the objective's maximizer is a
    vertex, so q tends to put all its mass on the worst group (the table's "Worst Risk").

    Args:
        initial: p0, where every task comes from.
        options: the keys of ``risk.tr`` (:class:`TrOptions`): the grid and η of the ascent step.

    Examples:
        >>> import torch
        >>> from armeta_rl.risk import WorstCasePrinciple
        >>> from armeta_rl.risk.groups import TrOptions
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> p0 = BoxUniform(TaskSpace(["x"], low=[0.0], high=[1.0]))
        >>> principle = WorstCasePrinciple(p0, TrOptions(groups_per_axis=3, step_size=0.1))
        >>> tasks = principle.propose(3)
        >>> tasks["params"] = torch.tensor([[0.1], [0.5], [0.9]])  # one task per group
        >>> _ = principle.update(tasks, torch.tensor([1.0, 2.0, 3.0]))
        >>> principle.weights(torch.tensor([1.0, 2.0, 3.0]), tasks)  # q moved to the worst group
        tensor([0.2333, 0.3333, 0.4333])
    """

    def __init__(self, initial: TaskDistribution, options: TrOptions = TrOptions()) -> None:
        super().__init__(initial, options)

    def _ascent_step(self, q: Tensor, group_losses: Tensor) -> Tensor:
        """q ← Π_Δ(q + η·L̄), the projected ascent step on the inner max of Eq. (3)."""
        return project_to_simplex(q + self.step_size * group_losses)


class GroupDROPrinciple(_GroupPrinciple):
    """``dro``: group DRO (Sagawa et al. 2020), min_θ max_{q∈Δ} Σ_g q_g L_g(θ) (paper Eq. (19)).

    q takes an exponentiated-gradient (mirror-ascent) step every meta-iteration:
    q ← q·exp(η·L̄) / Σ_g q_g·exp(η·L̄_g), computed in log space so large losses cannot overflow.

    Args:
        initial: p0, where every task comes from.
        options: the keys of ``risk.dro`` (:class:`DroOptions`): the grid and η of the
            exponentiated-gradient step.

    Examples:
        >>> import torch
        >>> from armeta_rl.risk import GroupDROPrinciple
        >>> from armeta_rl.risk.groups import DroOptions
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> p0 = BoxUniform(TaskSpace(["x"], low=[0.0], high=[1.0]))
        >>> principle = GroupDROPrinciple(p0, DroOptions(groups_per_axis=3, step_size=0.1))
        >>> tasks = principle.propose(3)
        >>> tasks["params"] = torch.tensor([[0.1], [0.5], [0.9]])  # one task per group
        >>> _ = principle.update(tasks, torch.tensor([1.0, 2.0, 3.0]))
        >>> principle.weights(torch.tensor([1.0, 2.0, 3.0]), tasks)  # q ∝ exp(η · group loss)
        tensor([0.3006, 0.3322, 0.3672])
    """

    def __init__(self, initial: TaskDistribution, options: DroOptions = DroOptions()) -> None:
        super().__init__(initial, options)

    def _ascent_step(self, q: Tensor, group_losses: Tensor) -> Tensor:
        """q ← q·exp(η·L̄) / Z, the exponentiated-gradient step on the inner max of Eq. (19)."""
        return torch.softmax(q.log() + self.step_size * group_losses, 0)
