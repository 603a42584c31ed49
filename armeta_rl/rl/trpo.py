"""TRPO pieces (Schulman et al. 2015) used by MAML-TRPO's outer step (MAML paper, Sec. 5.3): the
importance-sampled surrogate and mean KL of the trust-region problem (Eq. (14) there), and
conjugate gradient, Hessian-vector products of the mean KL, the natural-gradient step and the
backtracking line search that solve it (App. C there).

Parameters are handled as a list of tensors and flattened into one vector for the linear algebra.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from armeta_rl.rl.baseline import episode_mean
from armeta_rl.rl.policy import kl_divergence


def flatten(tensors: Sequence[Tensor]) -> Tensor:
    """Concatenate tensors into one flat vector.

    Examples:
        >>> import torch
        >>> from armeta_rl.rl.trpo import flatten
        >>> flatten([torch.ones(2, 2), torch.zeros(3)])
        tensor([1., 1., 1., 1., 0., 0., 0.])
    """
    return torch.cat([t.reshape(-1) for t in tensors])


def unflatten(vector: Tensor, like: Sequence[Tensor]) -> list[Tensor]:
    """Split a flat vector back into tensors shaped like ``like``.

    Examples:
        >>> import torch
        >>> from armeta_rl.rl.trpo import flatten, unflatten
        >>> like = [torch.ones(2, 2), torch.zeros(3)]  # e.g. a weight and a bias
        >>> unflatten(torch.arange(7.0), like)  # a step vector, back in the parameters' shapes
        [tensor([[0., 1.],
                [2., 3.]]), tensor([4., 5., 6.])]
        >>> torch.equal(flatten(unflatten(torch.arange(7.0), like)), torch.arange(7.0))
        True
    """
    out, start = [], 0
    for t in like:
        out.append(vector[start : start + t.numel()].view_as(t))
        start += t.numel()
    return out


def surrogate_loss(
    log_prob: Tensor, data_log_prob: Tensor, advantages: Tensor, mask: Tensor
) -> Tensor:
    """Per-task TRPO surrogate loss ``[K]``, −mean(π_θ(a|s)/q(a|s)·Â) over each task's episodes
    (Schulman et al. 2015, Eq. (14), negated to be minimized): ``log_prob`` is ln π_θ(a|s) of the
    policy being optimized and ``data_log_prob`` ln q(a|s) of the policy that sampled the actions,
    all ``[K, E, T]`` with the valid steps in ``mask``.

    Examples:
        >>> import torch
        >>> from armeta_rl.rl.trpo import surrogate_loss
        >>> log_prob = torch.zeros(1, 1, 3)  # the sampling policy itself: ratio 1
        >>> advantages, mask = torch.tensor([[[1.0, 2.0, 3.0]]]), torch.ones(1, 1, 3).bool()
        >>> surrogate_loss(log_prob, log_prob, advantages, mask)
        tensor([-2.])
    """
    ratio = (log_prob - data_log_prob).exp()
    return -episode_mean(ratio * advantages, mask)


def mean_kl(
    loc: Tensor, scale: Tensor, old_loc: Tensor, old_scale: Tensor, mask: Tensor
) -> Tensor:
    """Per-task mean KL ``[K]`` over each task's episodes of the diagonal Gaussian policy
    (``loc``, ``scale``) from the old one, the trust-region constraint's divergence (Schulman et
    al. 2015, Eq. (14); measured as KL(π ‖ π_old), pytorch-maml-rl's direction: both directions
    have the same Hessian, the Fisher matrix, at π = π_old).

    Examples:
        >>> import torch
        >>> from armeta_rl.rl.trpo import mean_kl
        >>> ones, mask = torch.ones(1, 1, 3, 2), torch.ones(1, 1, 3).bool()
        >>> mean_kl(ones, ones, 0 * ones, ones, mask)  # loc moved by one σ on both action axes
        tensor([1.])
    """
    return episode_mean(kl_divergence(loc, scale, old_loc, old_scale), mask)


def conjugate_gradient(
    matvec: Callable[[Tensor], Tensor], b: Tensor, iterations: int = 10, residual_tol: float = 1e-10
) -> tuple[Tensor, Tensor]:
    """Approximately solve A x = b for symmetric positive-definite A given x ↦ A x
    (Hestenes–Stiefel CG, ``iterations`` steps, stopping early when ‖r‖² < ``residual_tol``).

    Returns (x, A x). CG keeps the residual r = b − A x up to date, so A x = b − r costs no extra
    product (TRPO needs it for the step size, Schulman et al. 2015, App. C).

    Examples:
        >>> import torch
        >>> from armeta_rl.rl.trpo import conjugate_gradient
        >>> matrix = torch.diag(torch.tensor([2.0, 4.0]))
        >>> conjugate_gradient(lambda v: matrix @ v, torch.tensor([2.0, 4.0]))
        (tensor([1.0000, 1.0000]), tensor([2.0000, 4.0000]))
    """
    x = torch.zeros_like(b)
    r = b.clone()
    p = b.clone()
    r_dot_r = r @ r
    for _ in range(iterations):
        if r_dot_r.item() < residual_tol:
            break
        ap = matvec(p)
        alpha = r_dot_r / (p @ ap)
        x = x + alpha * p
        r = r - alpha * ap
        new_r_dot_r = r @ r
        p = r + (new_r_dot_r / r_dot_r) * p
        r_dot_r = new_r_dot_r
    return x, b - r


def meta_kl_hessian_vector_product(
    divergence: Callable[[list[Tensor]], Tensor],
    outputs: Sequence[Tensor],
    leaves: Sequence[Tensor],
    broadcast: Sequence[Tensor],
    adapted: Sequence[Tensor],
    params: Sequence[Tensor],
    damping: float = 1e-5,
) -> Callable[[Tensor], Tensor]:
    """v ↦ (∇²_θ KL(θ'(θ)) + damping·I) v for a KL taken at adapted parameters, exact and second
    order through the adaptation step.

    ``broadcast`` are the meta-parameters θ expanded to ``[K, ...]`` and ``adapted`` the per-task
    parameters θ'_k = θ − α∇L^in_k computed from them with ``create_graph=True``. ``outputs`` are
    the policy's outputs (e.g. loc, scale) computed from ``leaves`` (detached copies of
    ``adapted``) on the post-adaptation data, and ``divergence(outs)`` is the (weighted) KL of
    outputs ``outs`` against the current ones. At the current point the KL sits at its minimum,
    so its gradients in the outputs and in θ' vanish and the exact Hessian in θ is
    Σ_k J_kᵀ F_k J_k, with J_k = I − α∇²L^in_k (symmetric) and F_k = J_outᵀ H_out J_out the
    Gauss–Newton (Fisher) form of the KL's Hessian in θ'_k (H_out: the KL's Hessian in the
    outputs, elementwise). Each product is five backward passes over retained graphs, none
    recomputing a forward pass: ``J v`` (through the inner step, w.r.t. the broadcast θ),
    ``J_out (J v)`` (the reverse-over-reverse trick: differentiate the pullback of the outputs
    w.r.t. its cotangent), ``H_out (·)``, ``J_outᵀ (·)`` and ``Σ_k J_k (·)`` (to θ).

    Examples:
        >>> import torch
        >>> from armeta_rl.rl.trpo import meta_kl_hessian_vector_product
        >>> theta = torch.tensor([0.5], requires_grad=True)
        >>> broadcast = theta.expand(2, 1)  # K = 2 tasks
        >>> adapted = broadcast * 1.0  # θ'_k = θ: no inner step, J_k = I
        >>> leaf = adapted.detach().requires_grad_(True)
        >>> x = torch.tensor([[1.0], [2.0]])
        >>> loc = leaf * x  # the policy's output on each task's data
        >>> def kl(outs):  # a KL with unit curvature in loc
        ...     return 0.5 * ((outs[0] - loc.detach()) ** 2).sum()
        >>> hvp = meta_kl_hessian_vector_product(kl, [loc], [leaf], [broadcast], [adapted], [theta],
        ...                                      damping=0.0)
        >>> hvp(torch.tensor([1.0]))  # Σ_k x_k² · v
        tensor([5.])
    """
    outputs = list(outputs)
    output_leaves = [o.detach().requires_grad_(True) for o in outputs]
    divergence_grad = torch.autograd.grad(
        divergence(output_leaves), output_leaves, create_graph=True
    )
    probes = [torch.zeros_like(o, requires_grad=True) for o in outputs]
    pullback = torch.autograd.grad(outputs, leaves, probes, create_graph=True)

    def product(vector: Tensor) -> Tensor:
        pieces = unflatten(vector, params)
        cotangents = [piece.expand_as(b) for piece, b in zip(pieces, broadcast)]
        tangents = torch.autograd.grad(adapted, broadcast, cotangents, retain_graph=True)
        output_tangents = torch.autograd.grad(pullback, probes, tangents, retain_graph=True)
        curvature = torch.autograd.grad(
            divergence_grad, output_leaves, output_tangents, retain_graph=True
        )
        fisher = torch.autograd.grad(outputs, leaves, curvature, retain_graph=True)
        back = torch.autograd.grad(adapted, params, fisher, retain_graph=True)
        return flatten(back).detach() + damping * vector

    return product


def trust_region_step(
    gradient: Tensor, hvp: Callable[[Tensor], Tensor], max_kl: float, cg_iterations: int = 10
) -> Tensor:
    """The full natural-gradient step s = √(2δ / gᵀF⁻¹g)·F⁻¹g (Schulman et al. 2015, App. C;
    to be *subtracted* from θ), with
    F⁻¹g from conjugate gradient; its quadratic KL model ½ sᵀFs equals δ = ``max_kl`` (F s from
    conjugate gradient's residual: ``cg_iterations`` products in all).

    Examples:
        >>> import torch
        >>> from armeta_rl.rl.trpo import trust_region_step
        >>> step = trust_region_step(torch.tensor([1.0, 0.0]), hvp=lambda v: 2 * v, max_kl=0.01)
        >>> step, 0.5 * step @ (2 * step)  # its quadratic KL is max_kl
        (tensor([0.1000, 0.0000]), tensor(0.0100))
    """
    direction, product = conjugate_gradient(hvp, gradient, cg_iterations)
    half_curvature = 0.5 * (direction @ product)
    multiplier = torch.sqrt(half_curvature.clamp_min(1e-12) / max_kl)
    return direction / multiplier


def backtracking_line_search(
    evaluate: Callable[[Tensor], tuple[Tensor, Tensor]],
    theta: Tensor,
    step: Tensor,
    old_loss: Tensor,
    max_kl: float,
    max_steps: int = 15,
    ratio: float = 0.8,
) -> tuple[Tensor, int | None, Tensor, Tensor]:
    """Try θ − ratio^i·step for i = 0 … max_steps−1; accept the first that lowers the loss and
    keeps the KL within ``max_kl``.

    ``evaluate(θ)`` returns (loss, KL) at θ. Returns (new θ, accepted i, loss and KL at the new
    θ), or (θ, None, ``old_loss``, 0) when no step qualifies, in which case θ is unchanged.

    Examples:
        >>> import torch
        >>> from armeta_rl.rl.trpo import backtracking_line_search
        >>> theta = torch.tensor([1.0, 1.0])
        >>> def evaluate(t):  # (loss, KL from theta)
        ...     return (t**2).sum(), ((t - theta) ** 2).sum()
        >>> new, tried, loss, kl = backtracking_line_search(evaluate, theta, torch.ones(2),
        ...                                                 old_loss=torch.tensor(2.0), max_kl=1.0)
        >>> new, tried  # 0.8² · step: the first within the KL bound
        (tensor([0.3600, 0.3600]), 2)
    """
    fraction = 1.0
    for i in range(max_steps):
        candidate = theta - fraction * step
        loss, kl = evaluate(candidate)
        if loss.item() < old_loss.item() and kl.item() < max_kl:
            return candidate, i, loss, kl
        fraction *= ratio
    return theta, None, old_loss, torch.zeros_like(old_loss)
