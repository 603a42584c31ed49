"""The follower's objective, its score-function surrogate and its ascent step (paper Eqs. (6),
(17) and (14)).

The ascent step is the paper's Adam step, or a natural-gradient step of fixed KL
(:func:`natural_ascent_step`): the step direction F⁻¹∇_φJ with F the Fisher information of p_φ,
scaled so that each update moves p_φ by KL δ. Adam moves each parameter by about its rate per
update, so how far p_φ can move depends on how the flow is parametrized (a coordinate moved
through a conditioner network moves tens of times further than one moved by direct spline
parameters) and, under a rate divided by the run length, on the run length. The natural step
measures the move in the distribution itself.

The adversary maximizes J(φ) = E_{p_φ}[L(τ)] + λ·E_{p0}[ln p_φ(τ)] (Eq. (6)). Its gradient is

    ∇_φ J ≈ (1/K) Σ_k (L_k − V_k) ∇_φ ln p_φ(τ_k) + (λ/M) Σ_m ∇_φ ln p_φ(τ_m^0)

with τ_k ~ p_φ the tasks the leader was scored on (held fixed) and V a baseline (Eq.
(17)). The second term is the gradient of λ·E_{p0}[ln p_φ], estimated at draws
τ_m^0 ~ p0. The paper's Eq. (16) evaluates it at the base draws τ_k^{-M} whose
images NN_φ(τ_k^{-M}) are the tasks τ_k: those are draws of p0 for every φ (the flow moves their
images, not them), so that estimate is unbiased as well. What differs is its variance and its
coupling to the loss term: here the M = ``risk.ar.initial_samples`` (default 256) draws are fresh
and independent of the tasks, where the paper reuses the K (16 to 25) draws that generated them,
so its two terms are estimated from the same K points. The price is M extra log-density
evaluations per update. (The authors' code, lvyiqin/AR-MAML, also evaluates this term under the
flow before its batch min–max map into the box and only at draws whose inverse image lies in the
box; docs/protocol.md.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import Tensor

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.errors import ConfigError, TrainingDiverged
from armeta_rl.rl.trpo import flatten, trust_region_step, unflatten
from armeta_rl.tasks.distributions import entropy_estimate, kl_estimate
from armeta_rl.tasks.protocol import TASK_KEY

BASELINES = ("mean", "leave_one_out")
SIGNALS = ("loss", "regret")
STEPS = ("adam", "natural")
FISHER_DAMPING = 0.1
"""Added to the Fisher matrix of the natural step: its estimate from M samples has rank at most
M, and in the directions it misses the step would otherwise be unbounded."""


def regret(losses: Tensor, reference_losses: Tensor) -> Tensor:
    """The regret L(τ) − L*(τ) ``[K]`` of each task against a reference loss ``[K]`` (e.g. minus
    the best return any policy can get there): what the learner leaves on the table, free of how
    large the task's loss is in itself (regret-based environment design, Dennis et al. 2020)."""
    return losses - reference_losses


def standardized(advantages: Tensor, losses: Tensor) -> Tensor:
    """``advantages`` divided by the batch standard deviation of ``losses`` (unchanged when the
    losses are all equal): the loss term of the surrogate then has unit scale whatever the loss's
    units (MSE, returns), so λ is relative to the loss scale."""
    spread = losses.std() if losses.numel() > 1 else losses.new_zeros(())
    return advantages / spread if spread > 0 else advantages


def score_baseline(losses: Tensor, baseline: str = "mean") -> Tensor:
    """The baseline V of the score-function estimator (paper Eq. (17)): the batch mean (the
    paper's choice) or, per task, the mean of the other tasks' losses (independent of τ_k, hence
    exactly unbiased)."""
    if baseline == "mean":
        return losses.mean().expand_as(losses)
    if baseline == "leave_one_out":
        if losses.numel() < 2:
            raise ConfigError("risk.ar.baseline", baseline, "needs at least 2 tasks per update")
        return (losses.sum() - losses) / (losses.numel() - 1)
    raise ConfigError("risk.ar.baseline", baseline, "allowed: " + ", ".join(BASELINES))


def adversary_objective(losses: Tensor, lam: float, initial_log_prob: Tensor) -> Tensor:
    """Monte-Carlo estimate of the follower's objective J(θ, φ) = E_{p_φ}[L] + λ·E_{p0}[ln p_φ]
    (paper Eq. (6)): the mean of the losses ``[K]`` of tasks drawn from p_φ plus λ times the mean
    of ln p_φ at draws of p0 (``initial_log_prob`` ``[M]``)."""
    return losses.mean() + lam * initial_log_prob.mean()


def score_function_surrogate(
    advantages: Tensor, task_log_prob: Tensor, lam: float, initial_log_prob: Tensor
) -> Tensor:
    """A scalar whose gradient in φ is the score-function estimate of ∇_φ J (paper Eq. (17)):
    (1/K) Σ_k (L_k − V_k)·ln p_φ(τ_k) + (λ/M) Σ_m ln p_φ(τ_m^0), with ``advantages`` L_k − V_k
    ``[K]`` held fixed, ``task_log_prob`` ln p_φ(τ_k) ``[K]`` and ``initial_log_prob``
    ln p_φ(τ_m^0) ``[M]`` at draws of p0, both differentiable in φ."""
    return (advantages * task_log_prob).mean() + lam * initial_log_prob.mean()


def adversary_surrogate(
    adversary: FlowAdversary,
    tasks: TensorDictBase | Tensor,
    losses: Tensor,
    lam: float,
    initial_params: Tensor,
    baseline: str = "mean",
    log_prob: Callable[[Tensor], Tensor] | None = None,
    standardize: bool = False,
) -> tuple[Tensor, dict[str, float]]:
    """The surrogate of :func:`score_function_surrogate` (paper Eq. (17)) for ``tasks`` and their
    losses, with ln p_φ evaluated once for the tasks and the p0 draws together.

    Args:
        adversary: p_φ.
        tasks: the tasks ``{"params": [K, d], ...}`` (or their params) the losses belong to; they
            are held fixed and ln p_φ is re-evaluated at them.
        losses: per-task losses ``[K]`` (detached here).
        lam: Lagrange multiplier λ ≥ 0 of the KL(p0 ‖ p_φ) constraint.
        initial_params: ``[M, d]`` samples of p0, independent of the tasks.
        baseline: ``"mean"`` or ``"leave_one_out"``.
        log_prob: the function computing ln p_φ (default ``adversary.log_prob``; e.g. a compiled
            version of it).
        standardize: divide the advantages L_k − V_k by the batch standard deviation of the
            losses (:func:`standardized`; ``objective`` is then in those units too).

    Returns:
        ``(surrogate, stats)``: ascend ``surrogate``. ``stats`` holds Monte-Carlo estimates at the
        current φ that reuse the log-densities the surrogate needs: ``objective`` mean(L) +
        λ·mean ln p_φ(τ^0) of J, ``loss_mean``, ``entropy`` −mean ln p_φ(τ_k) (the τ_k are
        samples of p_φ) and ``kl_p0`` mean[ln p0(τ^0) − ln p_φ(τ^0)].

    Examples:
        >>> import torch
        >>> from armeta_rl.adversary import FlowAdversary, adversary_surrogate
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> _ = torch.manual_seed(0)
        >>> space = TaskSpace(["x"], low=[0.0], high=[1.0])
        >>> adversary = FlowAdversary(space, BoxUniform(space))  # p_φ = p0 = U[0, 1] at first
        >>> tasks = torch.tensor([[0.1], [0.5], [0.9]])
        >>> losses = torch.tensor([0.0, 1.0, 2.0])  # L - V = -1, 0, 1 with the mean baseline
        >>> surrogate, stats = adversary_surrogate(adversary, tasks, losses, lam=0.0,
        ...                                        initial_params=adversary.base.sample_params(16))
        >>> stats  # J = mean loss; ln p_φ = 0 on the unit box, so entropy and KL(p0 ‖ p_φ) are 0
        {'objective': 1.0, 'loss_mean': 1.0, 'entropy': -0.0, 'kl_p0': 0.0}
        >>> surrogate.backward()
        >>> torch.optim.SGD(adversary.parameters(), lr=0.5, maximize=True).step()  # ascend it
        >>> adversary.log_prob(tasks).exp().detach()  # density moved from x = 0.1 to x = 0.9
        tensor([0.4179, 1.0000, 1.1199], dtype=torch.float64)
    """
    params = tasks[TASK_KEY] if isinstance(tasks, TensorDictBase) else tasks
    losses = losses.detach().to(torch.float64)
    advantages = losses - score_baseline(losses, baseline)
    if standardize:
        advantages = standardized(advantages, losses)
    points = torch.cat([params.to(torch.float64), initial_params.to(torch.float64)]).detach()
    sizes = [len(params), len(initial_params)]
    log_p_tasks, log_p_initial = (log_prob or adversary.log_prob)(points).split(sizes)
    surrogate = score_function_surrogate(advantages, log_p_tasks, lam, log_p_initial)
    log_p_initial = log_p_initial.detach()
    scaled = standardized(losses, losses) if standardize else losses
    objective = adversary_objective(scaled, lam, log_p_initial)
    kl = kl_estimate(adversary.base.log_prob(initial_params), log_p_initial)
    return surrogate, {
        "objective": float(objective),
        "loss_mean": float(losses.mean()),
        "entropy": float(entropy_estimate(log_p_tasks.detach())),
        "kl_p0": float(kl),
    }


def surrogate_gradient(
    surrogate: Tensor, optimizer: torch.optim.Optimizer, phi: list[Tensor],
    grad_clip: float | None,
) -> Tensor:
    """Set the gradients of φ (``phi``, the parameters ``optimizer`` steps) to ∇_φ ``surrogate``,
    the estimate of ∇_φ J of paper Eq. (17), clipped to total norm ``grad_clip`` (``None``: not
    clipped), for the ascent step of Eq. (14) (second line); returns the norm before clipping."""
    optimizer.zero_grad(set_to_none=True)
    surrogate.backward()
    max_norm = math.inf if grad_clip is None else grad_clip
    return torch.nn.utils.clip_grad_norm_(phi, max_norm, foreach=True)


def fisher_vector_product(log_p: Tensor, phi: list[Tensor], damping: float = FISHER_DAMPING
                          ) -> Callable[[Tensor], Tensor]:
    """v ↦ (F̂ + damping·I) v, with F̂ = (1/n) Σ_i ∇_φ ln p_φ(τ_i) ∇_φ ln p_φ(τ_i)ᵀ the Fisher
    information of p_φ (Amari 1998) estimated from ``log_p`` = ln p_φ(τ_i) ``[n]`` at draws τ_i of
    p_φ (differentiable in ``phi``), for flat vectors over ``phi``. F̂ is positive semi-definite,
    and ½ sᵀF s is the KL between p_φ and p_{φ+s} to second order. Each product is three backward
    passes over the one forward pass behind ``log_p``: J v by the reverse-over-reverse trick
    (differentiating Jᵀu in u), then Jᵀ(J v).

    Examples:
        >>> import torch
        >>> from armeta_rl.adversary.objective import fisher_vector_product
        >>> mu = torch.zeros(1, dtype=torch.float64, requires_grad=True)
        >>> draws = torch.randn(100_000, dtype=torch.float64)  # a unit Gaussian with mean mu
        >>> product = fisher_vector_product(-0.5 * (draws - mu) ** 2, [mu], damping=0.0)
        >>> round(float(product(torch.ones(1, dtype=torch.float64))), 1)  # its Fisher: 1
        1.0
    """
    probe = torch.zeros_like(log_p, requires_grad=True)
    pullback = torch.autograd.grad(log_p, phi, probe, create_graph=True)

    def product(vector: Tensor) -> Tensor:
        tangent = torch.autograd.grad(pullback, probe, unflatten(vector, phi),
                                      retain_graph=True)[0]
        back = torch.autograd.grad(log_p, phi, tangent / len(log_p), retain_graph=True)
        return flatten(back).detach() + damping * vector

    return product


def natural_ascent_step(gradient: Tensor, fisher_product: Callable[[Tensor], Tensor],
                        max_kl: float) -> Tensor:
    """The step s = √(2δ / gᵀF⁻¹g)·F⁻¹g of natural-gradient ascent on J (Kakade 2001) with the
    trust-region length of TRPO (Schulman et al. 2015, App. C; F⁻¹g by conjugate gradient): its
    quadratic KL ½ sᵀF s is δ = ``max_kl``, whatever the flow's parametrization and the scale of
    J's gradient ``g``. Added to φ, it is the follower's step of paper Eq. (14), second line, with
    η_t ∇_φ J replaced by s."""
    return trust_region_step(gradient, fisher_product, max_kl)


@dataclass
class Follower:
    """The follower of the game: p_φ, how it steps and the settings of the estimate of Eq. (17):
    λ, the baseline, the p0 sample size M and the clipping norm (``None``: none).

    It steps by ``optimizer`` (Adam ascending J, ``maximize=True``) with its learning-rate
    ``scheduler`` (``None``: a constant rate), or, with ``max_kl`` = δ set (and no optimizer), by
    the natural step of KL δ (:func:`natural_ascent_step`), whose Fisher matrix is estimated at
    the M p0 draws pushed through the flow. ``log_prob`` computes ln p_φ (default
    ``adversary.log_prob``; e.g. a compiled version); ``standardize`` divides the advantages by
    the losses' batch standard deviation (:func:`standardized`: λ relative to the loss scale)."""

    adversary: FlowAdversary
    optimizer: torch.optim.Optimizer | None
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None
    lam: float = 0.0
    baseline: str = "mean"
    initial_samples: int = 256
    grad_clip: float | None = 1.0
    log_prob: Callable[[Tensor], Tensor] | None = None
    standardize: bool = False
    max_kl: float | None = None


def follower_step(follower: Follower, tasks: TensorDictBase | Tensor, losses: Tensor
                  ) -> dict[str, float]:
    """φ_{t+1} = φ_t + η_t ∇_φ J(θ_{t+1}, φ_t): the follower's ascent step (paper Eq. (14),
    second line), with the score-function estimate of Eq. (17) from the losses ``[K]`` of
    ``tasks`` at θ_{t+1}; φ, the optimizer's state and the schedule step in place. With
    ``follower.max_kl`` set, η_t ∇_φ J is the natural step of that KL
    (:func:`natural_ascent_step`), its Fisher matrix estimated at the M p0 draws pushed through
    the flow.

    Returns the surrogate's statistics at φ_t (``objective``, ``loss_mean``, ``entropy``,
    ``kl_p0``), ``grad_norm`` (before clipping) and ``lr`` (Adam's rate used) or ``step_kl``
    (the natural step's KL(p_φt ‖ p_φt+1), measured at its Fisher draws). It draws the M p0
    samples of the λ term and no other random numbers.

    Raises:
        TrainingDiverged: the losses, the surrogate or its gradient are not finite (φ not
            stepped), or the new φ or its log-density at ``tasks`` are not finite (φ stepped:
            the run's last checkpoint is the state to go back to).
    """
    params = tasks[TASK_KEY] if isinstance(tasks, TensorDictBase) else tasks
    losses = losses.detach().to(torch.float64)
    if not torch.isfinite(losses).all():
        raise TrainingDiverged(f"adversary update got non-finite losses: {losses.tolist()}")
    adversary, optimizer = follower.adversary, follower.optimizer
    log_prob = follower.log_prob or adversary.log_prob
    initial = adversary.base.sample_params(follower.initial_samples)
    surrogate, stats = adversary_surrogate(adversary, params, losses, follower.lam, initial,
                                           follower.baseline, log_prob, follower.standardize)
    if follower.max_kl is None:
        phi = [p for group in optimizer.param_groups for p in group["params"]]
        grad_norm = surrogate_gradient(surrogate, optimizer, phi, follower.grad_clip)
        if not _finite(surrogate, grad_norm):
            optimizer.zero_grad(set_to_none=True)
            raise _not_finite(surrogate, grad_norm)
        step_stats = {"lr": float(optimizer.param_groups[0]["lr"])}
        optimizer.step()
        if follower.scheduler is not None:
            follower.scheduler.step()
        optimizer.zero_grad(set_to_none=True)
        points = params
    else:
        phi = list(adversary.parameters())
        gradient = flatten(torch.autograd.grad(surrogate, phi))
        grad_norm = gradient.norm()
        if not _finite(surrogate, grad_norm):
            raise _not_finite(surrogate, grad_norm)
        with torch.no_grad():
            draws = adversary.push_forward(initial)[0]
        log_p = log_prob(draws)
        step = natural_ascent_step(gradient, fisher_vector_product(log_p, phi), follower.max_kl)
        with torch.no_grad():
            for parameter, change in zip(phi, unflatten(step, phi), strict=True):
                parameter.add_(change)
        points = torch.cat([params.to(draws), draws])
    largest = torch.nn.utils.get_total_norm(phi, norm_type=math.inf, foreach=True)
    with torch.no_grad():
        try:
            new_log_prob = log_prob(points)
        except AssertionError:  # normflows' spline asserts its bins are well formed
            new_log_prob = torch.full((1,), math.nan)
    if not (torch.isfinite(largest) and torch.isfinite(new_log_prob).all()):
        raise TrainingDiverged("adversary step produced non-finite parameters or log-densities")
    if follower.max_kl is not None:
        step_kl = kl_estimate(log_p.detach(), new_log_prob[len(params):])
        step_stats = {"step_kl": float(step_kl)}
    return {**stats, **step_stats, "grad_norm": float(grad_norm)}


def _finite(surrogate: Tensor, grad_norm: Tensor) -> bool:
    return bool(torch.isfinite(surrogate) and torch.isfinite(grad_norm))


def _not_finite(surrogate: Tensor, grad_norm: Tensor) -> TrainingDiverged:
    return TrainingDiverged(f"adversary surrogate or gradient is not finite (surrogate "
                            f"{float(surrogate)}, norm {float(grad_norm)})")
