"""The distribution adversary p_φ: a box-preserving normalizing flow on top of p0 (paper Sec. 3.1).

τ0 ~ p0, τ = g_φ(τ0) (paper Eq. (9)) and

    ln p_φ(τ) = ln p0(τ0) − Σ_i ln|det ∂g_i/∂τ^{i−1}|          (paper Eq. (10))

at sampling time, or equivalently ln p_φ(τ) = ln p0(g⁻¹(τ)) + ln|det ∂g⁻¹/∂τ| at any point of the
box through the inverse flow. Samples and log-densities are computed in float64.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from armeta_rl.adversary.flows import DEFAULT_FLOW, FLOW_KINDS, make_box_flow
from armeta_rl.errors import ConfigError
from armeta_rl.tasks.distributions import TaskDistribution, entropy_estimate
from armeta_rl.tasks.space import TaskSpace


class FlowAdversary(TaskDistribution):
    """p_φ(τ): the push-forward of ``base`` (p0) through a learnable bijection of the task box.

    It satisfies the adversary's contract (docs/architecture.md): samples always lie in the box;
    :meth:`log_prob` is an exact normalized density at any point of the box (``-inf`` outside),
    differentiable in φ at fixed τ, and equal to the log-probability returned by :meth:`sample`;
    p_φ = p0 at initialization; the entropy is available by Monte Carlo.

    Args:
        space: the task box.
        base: the initial distribution p0 on the same box.
        flow: ``"spline"`` (rational-quadratic spline coupling flow) or ``"planar"`` (the paper's
            leaky-ReLU planar flow); see :mod:`armeta_rl.adversary.flows`.
        **flow_kwargs: options of the flow (spline: ``layers``, ``bins``, ``hidden``, ``blocks``;
            planar: ``layers``, ``activation``, ``eps``).

    Examples:
        >>> import torch
        >>> from armeta_rl.adversary import FlowAdversary
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> space = TaskSpace(["goal_x", "goal_y"], low=[0.0, 0.0], high=[2.0, 1.0])
        >>> adversary = FlowAdversary(space, BoxUniform(space))  # p_φ = p0 at initialization
        >>> points = torch.tensor([[0.5, 0.5], [3.0, 0.5]], dtype=torch.float64)
        >>> adversary.log_prob(points).exp().detach()  # 1 / area of the 2 x 1 box; 0 outside
        tensor([0.5000, 0.0000], dtype=torch.float64)
    """

    def __init__(
        self,
        space: TaskSpace,
        base: TaskDistribution,
        flow: str = DEFAULT_FLOW,
        **flow_kwargs: int | float | str,
    ) -> None:
        if flow not in FLOW_KINDS:
            raise ConfigError("risk.ar.flow", flow, "allowed: " + ", ".join(FLOW_KINDS))
        if base.space != space:
            raise ConfigError("benchmark.space", base.space, f"p0 must live on the box {space}")
        super().__init__(space)
        self.base = base
        self.flow_kind = flow
        self.flow = make_box_flow(space, flow, **flow_kwargs)
        self.register_buffer("centre", (self.low + self.high) / 2, persistent=False)

    @torch.no_grad()
    def sample_with_log_prob(self, n: int) -> tuple[Tensor, Tensor]:
        """``n`` samples τ = g(τ0), τ0 ~ p0, and ln p_φ(τ) from the forward pass (Eq. (10));
        both float64 and detached."""
        return self.push_forward(self.base.sample_params(n))

    def push_forward(self, initial: Tensor) -> tuple[Tensor, Tensor]:
        """τ = g(τ0) for points ``initial = τ0 [n, d]`` of p0 (paper Eq. (9)), and ln p_φ(τ) =
        ln p0(τ0) − ln|det ∂g/∂τ0| (Eq. (10)); the random draw stays with the caller."""
        params, log_det = self.flow(initial)
        return params, self.base.log_prob(initial) - log_det

    def sample_params(self, n: int) -> Tensor:
        """``n`` identifiers ``[n, d]`` (float64) drawn from p_φ."""
        return self.sample_with_log_prob(n)[0]

    def log_prob(self, params: Tensor) -> Tensor:
        """Exact ln p_φ(τ) ``[n]`` (float64) at any ``params [n, d]``: ln p0(g⁻¹(τ)) +
        ln|det ∂g⁻¹/∂τ| inside the box (paper Eq. (10) through the inverse flow, the form of its
        Eq. (44)), ``-inf`` outside. Differentiable with respect to φ."""
        params = params.to(torch.float64)
        inside = self._inside(params)
        safe = torch.where(inside[:, None], params, self.centre)
        initial, log_det = self.flow.inverse(safe)
        return torch.where(inside, self.base.log_prob(initial) + log_det, -math.inf)

    @torch.no_grad()
    def entropy(self, n: int = 4096) -> Tensor:
        """Monte-Carlo entropy H[p_φ] = −E_{p_φ}[ln p_φ(τ)] from ``n`` samples (paper Eq. (12),
        :func:`~armeta_rl.tasks.distributions.entropy_estimate`); a detached float64 scalar."""
        return entropy_estimate(self.sample_with_log_prob(n)[1])
