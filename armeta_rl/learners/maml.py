"""MAML batched over tasks (Finn et al. 2017; the paper's AR-MAML, Eq. (7), and Algorithm 1).

The adapted loss of one task, L(D^Q_τ; θ − γ∇_θ L(D^S_τ; θ)) (the bracket of Eq. (7)), is written
for one task with ``torch.func`` (:meth:`MAMLLeader.adapt`, :meth:`MAMLLeader.query_loss`) and
``vmap``-ed over the task dimension, so a meta-batch costs one batched forward/backward and no
Python loop over tasks. Two documented switches (docs/speed-options.md) compute the same function
faster where a benchmark showed it: ``learner.maml.adaptation=low_rank`` (the inner steps as
low-rank weight updates, :mod:`armeta_rl.learners.low_rank`) and ``learner.maml.compile``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor, nn
from torch.func import functional_call, grad, vmap

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.compiling import compile_backend, maybe_compile
from armeta_rl.errors import ConfigError
from armeta_rl.fields import Section, above, at_least, each, key, one_of, register
from armeta_rl.learners.base import (
    OneNetworkLeader,
    TaskWeights,
    mean_squared_error,
    sizes,
)
from armeta_rl.learners.low_rank import low_rank_query_losses
from armeta_rl.learners.mlp import MLP, make_mlp

Params = dict[str, Tensor]

ADAPTATIONS = ("vmap", "low_rank")


def sgd_step(params: Params, gradients: Params, lr: float) -> Params:
    """θ' = θ − γ∇_θ L(D^S_τ; θ), the inner (adaptation) step inside paper Eq. (7), for the
    named parameters ``params`` and their ``gradients``, step size γ = ``lr``."""
    return {name: p - lr * gradients[name] for name, p in params.items()}


@register("learner.maml")
@dataclass(frozen=True)
class MamlOptions(Section):
    """``learner.maml``: MAML's keys, their types, ranges and defaults.

    Attributes:
        hidden: the hidden widths of the MLP the builder makes (a leader built from Python is
            handed its network and ignores it).
        inner_lr: γ, the step size of the inner (adaptation) SGD steps.
        inner_steps: number of inner steps.
        first_order: drop the second-order term (treat ∇_θ L^S as a constant).
        outer_lr: Adam learning rate of the meta-update.
        adaptation: how the batched adapted losses are computed: ``"vmap"``, the per-task form
            vmapped, or ``"low_rank"`` (an :class:`~armeta_rl.learners.mlp.MLP` only); the same
            function of θ, different speed and rounding (docs/speed-options.md).
        compile: ``torch.compile`` the batched loss (the meta-update, the follower's losses at
            θ_{t+1} and the evaluation): ``False``, ``True`` (inductor) or a backend name; see
            :mod:`armeta_rl.compiling`.
    """

    hidden: list[int] = each(at_least(1), default=[128, 128, 128])  # the paper's MLP: 3 × 128, ReLU
    # 0.01, not the paper's 1e-3: MAML reaches the paper's MSE with it (docs/notes/history.md)
    inner_lr: float = above(0, default=0.01)
    inner_steps: int = at_least(1, default=1)
    first_order: bool = key(default=False)
    outer_lr: float = above(0, default=0.001)
    # vmap (any network) or low_rank (the same maths without per-task weights, faster on small
    # support sets: the sinusoid benchmarks choose it; see docs/speed-options.md)
    adaptation: str = one_of(*ADAPTATIONS, default="vmap")
    # torch.compile the batched MAML loss: true (inductor) or a backend; pays on long runs only
    # (see docs/speed-options.md); checked by armeta_rl.compiling
    compile: Any = key(default=False)


class MAMLLeader(OneNetworkLeader):
    """MAML on regression data ``{"support": {"x", "y"}, "query": {"x", "y"}}``, metric MSE.

    Args:
        model: the network; its parameters are θ.
        collector: produces support/query data for a batch of tasks.
        options: the keys of ``learner.maml`` (:class:`MamlOptions`).

    Examples:
        >>> import torch
        >>> from armeta_rl.collectors import SinusoidCollector
        >>> from armeta_rl.learners import MAMLLeader, make_mlp
        >>> from armeta_rl.learners.maml import MamlOptions
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> _ = torch.manual_seed(0)
        >>> options = MamlOptions(inner_lr=0.01, inner_steps=1)
        >>> leader = MAMLLeader(make_mlp(1, 1, hidden=[16]), SinusoidCollector(), options)
        >>> space = TaskSpace(["amplitude", "phase"], low=[0.1, 0.0], high=[5.0, 3.1416])
        >>> data = leader.collect(BoxUniform(space).sample(4))
        >>> with torch.no_grad():  # θ's query MSE, without adapting
        ...     error = leader.model(data["query", "x"]) - data["query", "y"]
        >>> round(float(error.square().mean()), 2), leader.metric
        (8.56, 'mse')
        >>> round(float(leader.evaluate(data).mean()), 2)  # after one step on the support
        8.19
        >>> per_task, _ = leader.step(data, weights=lambda losses: torch.full_like(losses, 0.25))
    """

    metric = "mse"

    def __init__(
        self,
        model: nn.Module,
        collector: TaskCollector,
        options: MamlOptions = MamlOptions(),
    ) -> None:
        if options.adaptation == "low_rank" and not isinstance(model, MLP):
            raise ConfigError("learner.maml.adaptation", options.adaptation,
                              f"needs the package's MLP, not a {type(model).__name__}; use vmap")
        self.model, self.collector = model, collector
        self.inner_lr, self.inner_steps = options.inner_lr, int(options.inner_steps)
        self.first_order = options.first_order
        # The fused Adam kernel: one op for all parameters.
        self.optimizer = torch.optim.Adam(model.parameters(), lr=options.outer_lr, fused=True)
        self._support_gradient = grad(self._mse)
        self._batched_loss = (
            self._low_rank_losses if options.adaptation == "low_rank"
            else vmap(self.query_loss, in_dims=(None, 0, 0, 0, 0))
        )
        self._training_loss = maybe_compile(
            self._batched_loss, compile_backend("learner.maml.compile", options.compile)
        )

    def _mse(self, params: Params, x: Tensor, y: Tensor) -> Tensor:
        """L(D; θ): the mean squared error of the network with parameters ``params``."""
        return mean_squared_error(functional_call(self.model, params, (x,), tie_weights=False), y)

    def adapt(self, params: Params, x: Tensor, y: Tensor) -> Params:
        """θ'_τ = θ − γ∇_θ L(D^S_τ; θ) on one task's support set ``(x, y)`` (Eq. (7); Algorithm 1,
        inner loop), ``inner_steps`` times."""
        for _ in range(self.inner_steps):
            gradients = self._support_gradient(params, x, y)
            if self.first_order:
                gradients = {name: g.detach() for name, g in gradients.items()}
            params = sgd_step(params, gradients, self.inner_lr)
        return params

    def query_loss(
        self, params: Params, support_x: Tensor, support_y: Tensor, query_x: Tensor, query_y: Tensor
    ) -> Tensor:
        """L(D^Q_τ; θ'_τ) of one task (the loss inside Eq. (7)), from plain tensors."""
        return self._mse(self.adapt(params, support_x, support_y), query_x, query_y)

    def _low_rank_losses(
        self, params: Params, support_x: Tensor, support_y: Tensor, query_x: Tensor,
        query_y: Tensor,
    ) -> Tensor:
        """L(D^Q_τ; θ'_τ) of every task ``[K]`` with low-rank inner updates."""
        return low_rank_query_losses(
            self.model, params, support_x, support_y, query_x, query_y,
            self.inner_lr, self.inner_steps, self.first_order,
        )

    def task_losses(self, data: TensorDict, params: Params | None = None) -> Tensor:
        """Post-adaptation query loss of every task ``[K]``, differentiable w.r.t. θ.

        The vmap runs over plain tensors rather than the TensorDict (less per-call overhead)."""
        return self._losses(self._batched_loss, data, params)

    def _losses(self, batched_loss: Callable[..., Tensor], data: TensorDict,
                params: Params | None = None) -> Tensor:
        params = dict(self.model.named_parameters()) if params is None else params
        support, query = data["support"], data["query"]
        return batched_loss(params, support["x"], support["y"], query["x"], query["y"])

    def step(self, data: TensorDict, weights: TaskWeights) -> tuple[TensorDict, dict[str, float]]:
        """Meta-update θ ← Adam(∇_θ Σ_k w_k L_k) (paper Eq. (15), weighted) on the support/query
        ``data`` ``[K]``; returns the per-task ``"loss"`` before the update."""
        losses = self._losses(self._training_loss, data)
        self.descend(losses, weights)
        return TensorDict({"loss": losses.detach()}, batch_size=losses.shape), {}

    def evaluate(self, data: TensorDict) -> Tensor:
        """Post-adaptation query MSE per task ``[K]`` of ``data`` at the current θ (no
        meta-gradient kept)."""
        with torch.no_grad():  # torch.func.grad still differentiates the inner step
            return self._losses(self._training_loss, data)


def build_maml(options: MamlOptions, collector: TaskCollector, device: torch.device,
               model: Mapping[str, Any]) -> MAMLLeader:
    """MAML with ``options``, its MLP sized by the collector, with the head the benchmark's
    ``model`` choices name, on ``device``."""
    head = model.get("head", "none")
    target = getattr(collector, "target", None)
    if head == "tied_angle" and target != "next":
        raise ConfigError("benchmark.model.head", head,
                          f"predicts the next observation: needs benchmark.collector.target=next, "
                          f"not {target}")
    network = make_mlp(*sizes(collector), options.hidden, head).to(device)
    return MAMLLeader(network, collector, options)
