"""MAML's inner SGD steps on an :class:`~armeta_rl.learners.mlp.MLP` as low-rank weight updates.

For a layer z = h W + b and a support set of n points, the gradient of the support loss is
∇_W L = H_sᵀ δ and ∇_b L = 1ᵀ δ, where H_s ``[n, fan_in]`` holds the layer's inputs and
δ = ∂L/∂Z_s ``[n, fan_out]`` the loss's gradient at its pre-activations. So the inner step of
paper Eq. (7) and Algorithm 1, θ' = θ − γ∇_θ L(D^S_τ; θ), moves W by a matrix of rank at most n,
and any input h passes through the adapted layer as

    h W' + b' = h W + b + (h H_sᵀ + 1) Δ,        Δ = −γ δ,

with no per-task ``[fan_in, fan_out]`` weights. After k steps the updates stack: H_s and Δ gain
n rows per step. The product h W with the shared W is one matrix product for all tasks at once;
the per-task part costs O(rows · n · width). This is the same function of θ as
:meth:`MAMLLeader.query_loss`, so its meta-gradient (second order through δ and H_s, or first
order with both held constant) is the same too, up to rounding.

It pays when the support set is small against the layer widths (few-shot regression: 5 points
and 128 units); with larger support and query sets (system identification: 10 and 190 points) the
thin per-task products cost more than they save. ``python -m benchmarks.timing
bench_speed_options`` measures it against the vmapped form (docs/speed-options.md).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.func import grad

from armeta_rl.learners.base import mean_squared_error
from armeta_rl.learners.mlp import MLP, relu

Params = dict[str, Tensor]
Layers = list[tuple[Tensor, Tensor]]
Update = tuple[Tensor, Tensor]
"""One layer's accumulated inner steps: the support inputs H_s ``[K, m, fan_in]`` and the scaled
gradients Δ ``[K, m, fan_out]`` of all steps so far, stacked along m."""


def _forward(
    layers: Layers, x: Tensor, updates: list[Update] | None, shifts: list[Tensor] | None = None
) -> tuple[Tensor, list[Tensor]]:
    """Outputs ``[K, n, out]`` of the adapted network for inputs ``x [K, n, in]`` and the inputs
    of every layer. ``shifts`` (zeros) are added to the pre-activations so that the gradient
    with respect to them is δ."""
    inputs, h, last = [], x, len(layers) - 1
    for index, (weight, bias) in enumerate(layers):
        inputs.append(h)
        z = h @ weight + bias
        if updates is not None:
            rows, steps = updates[index]
            z = torch.baddbmm(z, h @ rows.transpose(1, 2) + 1.0, steps)
        if shifts is not None:
            z = z + shifts[index]
        h = relu(z) if index < last else z
    return h, inputs


def _descent_objective(
    shifts: list[Tensor], layers: Layers, updates: list[Update] | None, x: Tensor, y: Tensor,
    inner_lr: float,
) -> tuple[Tensor, list[Tensor]]:
    """−γ Σ_τ L(D^S_τ) (the per-task losses are independent, so the gradient with respect to task
    τ's pre-activations is task τ's own Δ), with the layers' inputs as auxiliary output."""
    out, inputs = _forward(layers, x, updates, shifts)
    return -inner_lr * mean_squared_error(out, y, (1, 2)).sum(), inputs


_inner_step = grad(_descent_objective, has_aux=True)
"""The scaled gradients Δ of every layer (with respect to the shifts) and the layers' inputs."""


def low_rank_query_losses(
    model: MLP,
    params: Params,
    support_x: Tensor,
    support_y: Tensor,
    query_x: Tensor,
    query_y: Tensor,
    inner_lr: float,
    inner_steps: int,
    first_order: bool,
) -> Tensor:
    """Post-adaptation query MSE ``[K]`` of every task, L(D^Q_τ; θ'_τ) with θ'_τ after
    ``inner_steps`` SGD steps of size γ = ``inner_lr`` on D^S_τ (paper Algorithm 1), for data
    ``[K, n, features]`` and θ = ``params`` (``model``'s parameter names)."""
    layers = model.layers(params)
    updates: list[Update] | None = None
    for _ in range(inner_steps):
        shifts = [support_x.new_zeros(*support_x.shape[:2], w.shape[1]) for w, _ in layers]
        deltas, inputs = _inner_step(shifts, layers, updates, support_x, support_y, inner_lr)
        if first_order:
            deltas, inputs = [d.detach() for d in deltas], [h.detach() for h in inputs]
        step = list(zip(inputs, deltas))
        updates = step if updates is None else [
            (torch.cat([rows, h], 1), torch.cat([steps, d], 1))
            for (rows, steps), (h, d) in zip(updates, step)
        ]
    out, _ = _forward(layers, query_x, updates)
    return mean_squared_error(out, query_y, (1, 2))
