"""Box-preserving normalizing flows: bijections of the task box onto itself (paper Sec. 3.1).

The paper's adversary (appendix "Distribution Adversary Implementations") maps the flow output into
the box by a min-max over the current batch, which makes the "density" depend on the batch. Here
every flow is a bijection of the closed box onto itself, so
ln p_φ(τ) = ln p0(g⁻¹(τ)) + ln|det ∂g⁻¹/∂τ| (paper Eq. (10)) is an exact, normalized
density at any point of the box:

* ``spline`` (default): affine map of the box onto [0, 1]^d, a stack of normflows
  ``CoupledRationalQuadraticSpline`` layers with ``tails=None`` (rational-quadratic splines that map
  [0, 1] onto itself; one layer on a 2-D box), alternating masks, and the affine map back.
* ``planar`` (the paper's choice, two planar layers): box → [0, 1]^d → logit → normflows
  ``Planar`` layers on R^d → sigmoid → box; tanh activation by default, since the paper's leaky
  ReLU makes the score-function gradient biased (see :class:`PlanarBoxFlow`).

The two affine maps have constant Jacobians that cancel, so they add nothing to the log-determinant.
Both flows are the identity at initialization (p_φ = p0) and run in float64.
"""

from __future__ import annotations

import inspect
import math

import torch
from normflows.flows import CoupledRationalQuadraticSpline, Flow, Planar, Reverse
from normflows.flows.neural_spline.coupling import PiecewiseRationalQuadraticCDF
from normflows.transforms import Logit
from normflows.utils.splines import DEFAULT_MIN_DERIVATIVE
from torch import Tensor, nn

from armeta_rl.errors import ConfigError
from armeta_rl.tasks.space import TaskSpace

FLOW_KINDS = ("spline", "planar")
DEFAULT_FLOW = "spline"
"""The flow of ``risk.ar.flow`` (:class:`~armeta_rl.adversary.options.ArOptions`),
:class:`~armeta_rl.adversary.flow_adversary.FlowAdversary` and :func:`make_box_flow` unless
told otherwise: exact and box-preserving."""

IDENTITY_DERIVATIVE = math.log(math.expm1(1.0 - DEFAULT_MIN_DERIVATIVE))
"""Pre-softplus knot derivative that gives a rational-quadratic spline slope one (identity)."""


class BoxFlow(nn.Module):
    """A bijection g of the closed box onto itself built from normflows layers, in float64.

    ``forward`` is the sampling direction τ = g(τ0); ``inverse`` is τ0 = g⁻¹(τ). Both return the
    image and ln|det| of the map they apply, shape ``[n]``.
    """

    def __init__(self, space: TaskSpace, layers: list[Flow]) -> None:
        super().__init__()
        self.space = space
        self.layers = nn.ModuleList(layers)
        low, high = space.bounds(torch.float64)
        self.register_buffer("low", low, persistent=False)
        self.register_buffer("high", high, persistent=False)
        self.register_buffer("width", high - low, persistent=False)
        self.to(torch.float64)
        self.reset_identity()

    def reset_identity(self) -> None:
        """Set the parameters so that the flow is the identity map (p_φ = p0)."""
        raise NotImplementedError

    def _enter(self, unit: Tensor) -> Tensor:
        """Prepare a point of [0, 1]^d for the first layer."""
        return unit

    def _between(self, x: Tensor) -> Tensor:
        """Applied after every layer (e.g. to undo rounding outside [0, 1])."""
        return x

    def _run(self, params: Tensor, inverse: bool) -> tuple[Tensor, Tensor]:
        x = self._enter((params.to(torch.float64) - self.low) / self.width)
        log_det: Tensor | float = 0.0
        for layer in reversed(self.layers) if inverse else self.layers:
            x, layer_log_det = layer.inverse(x) if inverse else layer(x)
            log_det = log_det + layer_log_det
            x = self._between(x)
        return (self.low + x * self.width).clamp(self.low, self.high), log_det

    def forward(self, params: Tensor) -> tuple[Tensor, Tensor]:
        """τ = g(τ0) = g_M ∘ … ∘ g_1(τ0) (paper Eq. (9)) for ``params = τ0 [n, d]`` in the box,
        and ln|det ∂g/∂τ0| = Σ_i ln|det ∂g_i/∂τ^{i−1}| ``[n]``, the sum of Eq. (10)."""
        return self._run(params, inverse=False)

    def inverse(self, params: Tensor) -> tuple[Tensor, Tensor]:
        """τ0 = g⁻¹(τ) for ``params = τ [n, d]`` in the box, and ln|det ∂g⁻¹/∂τ| ``[n]``."""
        return self._run(params, inverse=True)


class SplineBoxFlow(BoxFlow):
    """Rational-quadratic spline coupling flow on [0, 1]^d (Durkan et al., normflows).

    Each layer is a ``CoupledRationalQuadraticSpline`` with ``tails=None`` (a monotone spline of
    [0, 1] onto itself); masks alternate between layers and the identity half of each coupling gets
    normflows' unconditional spline, so every layer moves every coordinate. For ``d == 1`` there is
    nothing to condition on and each layer is normflows' unconditional
    ``PiecewiseRationalQuadraticCDF``.

    On a 2-D box one coupling layer is already the full autoregressive factorization
    p(τ1)·p(τ2 | τ1): an unconditional spline on τ1 and a spline on τ2 whose knots are a function of
    τ1. So ``layers`` defaults to 1 there, which halves the cost of the adversary's update against
    two layers; other dimensions default to 2.

    Args:
        space: the task box.
        layers: number of spline layers (``None``: 1 on a 2-D box, else 2).
        bins: spline bins per coordinate.
        hidden: hidden units of each coupling's residual network.
        blocks: residual blocks of each coupling's network.

    Examples:
        >>> import torch
        >>> from armeta_rl.adversary import SplineBoxFlow
        >>> from armeta_rl.tasks import TaskSpace
        >>> flow = SplineBoxFlow(TaskSpace(["m", "l"], low=[0.4, 0.4], high=[1.6, 1.6]))
        >>> points = torch.tensor([[0.5, 1.0], [1.5, 0.7]], dtype=torch.float64)
        >>> image, log_det = flow(points)  # the identity at initialization
        >>> image.detach()  # each point maps to itself
        tensor([[0.5000, 1.0000],
                [1.5000, 0.7000]], dtype=torch.float64)
        >>> log_det.detach()  # log |det J| = 0: the density is unchanged
        tensor([0., 0.], dtype=torch.float64)
    """

    def __init__(self, space: TaskSpace, layers: int | None = None, bins: int = 8,
                 hidden: int = 32, blocks: int = 2) -> None:
        if layers is None:
            layers = 1 if space.dim == 2 else 2
        for key, value in (("layers", layers), ("bins", bins), ("hidden", hidden)):
            if not isinstance(value, int) or value < 1:
                raise ConfigError(f"risk.ar.flow_kwargs.{key}", value, "must be an integer >= 1")
        if not isinstance(blocks, int) or blocks < 0:
            raise ConfigError("risk.ar.flow_kwargs.blocks", blocks, "must be an integer >= 0")
        if space.dim == 1:
            flows = [PiecewiseRationalQuadraticCDF([1], num_bins=bins, tails=None)
                     for _ in range(layers)]
        else:
            flows = [CoupledRationalQuadraticSpline(space.dim, blocks, hidden, num_bins=bins,
                                                    tails=None, reverse_mask=i % 2 == 1)
                     for i in range(layers)]
        super().__init__(space, flows)

    @torch.no_grad()
    def reset_identity(self) -> None:
        """Make every spline the identity: equal width/height logits (uniform bins) and knot
        derivatives softplus⁻¹(1 − min_derivative) + min_derivative = 1. In a coupling layer the
        last layer of the conditioner network is zeroed and its bias carries these constants (as
        normflows' ``identity_init`` does for the unconditional spline, which is reset too)."""
        for layer in self.layers:
            splines = [layer] if self.space.dim == 1 else [layer.prqct.unconditional_transform]
            for spline in splines:
                spline.unnormalized_widths.zero_()
                spline.unnormalized_heights.zero_()
                spline.unnormalized_derivatives.fill_(IDENTITY_DERIVATIVE)
            if self.space.dim > 1:
                bins = layer.prqct.num_bins
                final = layer.prqct.transform_net.final_layer
                final.weight.zero_()
                bias = final.bias.view(layer.prqct.num_transform_features, 3 * bins + 1)
                bias[:, : 2 * bins] = 0.0
                bias[:, 2 * bins :] = IDENTITY_DERIVATIVE

    def _between(self, x: Tensor) -> Tensor:
        return x.clamp(0.0, 1.0)


PLANAR_ACTIVATIONS = ("tanh", "leaky_relu")


class InvertiblePlanar(Planar):
    """normflows' ``Planar`` layer f(z) = z + û·h(wᵀz + b) with an inverse for ``tanh`` too.

    For ``leaky_relu`` normflows' algebraic inverse is used: on α = wᵀz + b the layer acts as
    α ↦ α(1 + a·wᵀû) with a > 0 the active slope and wᵀû > −1, so the sign of wᵀy + b picks the
    branch. For ``tanh``, α solves the monotone scalar equation α + c·tanh(α) = wᵀy + b with
    c = wᵀû > −1 and |α − (wᵀy + b)| ≤ |c|; it is found without gradients by Newton steps kept
    inside that bracket, and one final Newton step with gradients gives the exact first-order
    derivatives in φ and y (implicit function theorem).
    """

    def hat_u(self) -> Tensor:
        """û = u + (softplus(wᵀu) − 1 − wᵀu)·w/‖w‖², the reparametrisation that keeps wᵀû > −1."""
        inner = (self.w * self.u).sum()
        return self.u + (nn.functional.softplus(inner) - 1 - inner) * self.w / self.w.pow(2).sum()

    def inverse(self, z: Tensor) -> tuple[Tensor, Tensor]:
        if self.act != "tanh":
            return super().inverse(z)
        u = self.hat_u()
        c = (self.w * u).sum()
        target = (self.w * z).sum(-1) + self.b
        alpha = _solve_planar_tanh(target.detach(), c.detach())
        slope = 1 + c * (1 - torch.tanh(alpha).pow(2))
        alpha = alpha - (alpha + c * torch.tanh(alpha) - target) / slope
        slope = 1 + c * (1 - torch.tanh(alpha).pow(2))
        return z - u * torch.tanh(alpha)[:, None], -slope.log()


@torch.no_grad()
def _solve_planar_tanh(target: Tensor, c: Tensor, max_iterations: int = 100) -> Tensor:
    """α with α + c·tanh(α) = target, elementwise (c > −1 makes the left side increasing)."""
    low, high = target - c.abs(), target + c.abs()
    alpha = target - c * torch.tanh(target)
    for _ in range(max_iterations):
        tanh = torch.tanh(alpha)
        residual = alpha + c * tanh - target
        low = torch.where(residual < 0, alpha, low)
        high = torch.where(residual > 0, alpha, high)
        newton = alpha - residual / (1 + c * (1 - tanh * tanh))
        inside = (newton >= low) & (newton <= high)
        updated = torch.where(inside, newton, (low + high) / 2)
        converged = ((updated - alpha).abs() <= 1e-15 * (1 + alpha.abs())).all()
        alpha = updated
        if converged:
            break
    return alpha


class PlanarBoxFlow(BoxFlow):
    """Planar flows (Rezende & Mohamed 2015; the paper's adversary) between a logit and a sigmoid,
    so that they map the open box onto itself: box → [0, 1]^d → logit → planar layers on R^d →
    sigmoid → box.

    ``activation="tanh"`` (default) gives a smooth density. The paper's ``"leaky_relu"`` has an
    exact algebraic inverse, but its log-determinant jumps across each hinge wᵀz + b = 0 and the
    hinges move with φ, so p_φ(τ) is discontinuous in τ along φ-dependent surfaces: the
    score-function estimator (paper Eq. (17)) then misses the boundary term of
    ∇_φ E_{p_φ}[L] and is biased once the flow has left the identity. It is kept for reproducing
    the paper only. The unit-box coordinate is clamped to [eps, 1 − eps] before the logit so that
    points on the box faces keep a finite log-density (the clamp changes the map within eps of a
    face only).

    Args:
        space: the task box.
        layers: number of planar layers (the paper uses 2).
        activation: ``"tanh"`` or ``"leaky_relu"``.
        eps: clamp of the unit-box coordinate before the logit.

    Examples:
        >>> import torch
        >>> from armeta_rl.adversary import PlanarBoxFlow
        >>> from armeta_rl.tasks import TaskSpace
        >>> flow = PlanarBoxFlow(TaskSpace(["x"], low=[0.0], high=[2.0]), layers=2)
        >>> points = torch.tensor([[0.5], [1.5]], dtype=torch.float64)
        >>> back, _ = flow.inverse(flow(points)[0])
        >>> back.detach()  # the points it was given: the flow is invertible
        tensor([[0.5000],
                [1.5000]], dtype=torch.float64)
    """

    def __init__(self, space: TaskSpace, layers: int = 2, activation: str = "tanh",
                 eps: float = 1e-12) -> None:
        if not isinstance(layers, int) or layers < 1:
            raise ConfigError("risk.ar.flow_kwargs.layers", layers, "must be an integer >= 1")
        if activation not in PLANAR_ACTIVATIONS:
            raise ConfigError("risk.ar.flow_kwargs.activation", activation,
                              "allowed: " + ", ".join(PLANAR_ACTIVATIONS))
        if not 0.0 < eps < 0.5:
            raise ConfigError("risk.ar.flow_kwargs.eps", eps, "must lie in (0, 0.5)")
        planars = [InvertiblePlanar((space.dim,), act=activation) for _ in range(layers)]
        super().__init__(space, [Reverse(Logit(alpha=0.0)), *planars, Logit(alpha=0.0)])
        self.eps = eps

    @torch.no_grad()
    def reset_identity(self) -> None:
        """Make every planar layer the identity, keeping its (random) w and b: with
        u = ln(e − 1)·w/‖w‖² we get softplus(wᵀu) = 1 and û = 0."""
        for layer in self.layers:
            if isinstance(layer, Planar):
                layer.u.copy_(math.log(math.e - 1.0) * layer.w / layer.w.pow(2).sum())

    def _enter(self, unit: Tensor) -> Tensor:
        return unit.clamp(self.eps, 1.0 - self.eps)


def make_box_flow(
    space: TaskSpace, kind: str = DEFAULT_FLOW, **kwargs: int | float | str
) -> BoxFlow:
    """Build the box flow named ``kind`` (``spline`` or ``planar``) with its keyword options.

    Examples:
        >>> from armeta_rl.adversary import make_box_flow
        >>> from armeta_rl.tasks import TaskSpace
        >>> space = TaskSpace(["x", "y", "z"], low=[0, 0, 0], high=[1, 1, 1])
        >>> type(make_box_flow(space, "spline", bins=4)).__name__
        'SplineBoxFlow'
        >>> make_box_flow(space, "planar", bins=4)
        Traceback (most recent call last):
        ...
        armeta_rl.errors.ConfigError: config key 'risk.ar.flow_kwargs' = ['bins']: the planar ...
    """
    flows = {"spline": SplineBoxFlow, "planar": PlanarBoxFlow}
    if kind not in flows:
        raise ConfigError("risk.ar.flow", kind, "allowed: " + ", ".join(FLOW_KINDS))
    options = [name for name in inspect.signature(flows[kind]).parameters if name != "space"]
    unknown = sorted(set(kwargs) - set(options))
    if unknown:
        allowed = f"the {kind} flow accepts: {', '.join(options)}"
        raise ConfigError("risk.ar.flow_kwargs", unknown, allowed)
    return flows[kind](space, **kwargs)
