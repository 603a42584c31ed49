"""ANIL, "Almost No Inner Loop" (Raghu et al. 2020, "Rapid Learning or Feature Reuse?"): MAML
whose inner loop adapts the network's last layer (the head) only; the body's features are
meta-learned by the outer loop and reused unchanged by every task.

For a task τ with support set D^S and query set D^Q, and θ = (θ_body, θ_head):

    θ'_head = θ_head − γ ∇_{θ_head} L(D^S; θ_body, θ_head)        (inner step, head only)
    L_τ(θ)  = L(D^Q; θ_body, θ'_head)                              (adapted query loss)

The outer loop is MAML's: θ ← Adam(∇_θ Σ_k w_k L_k(θ)), batched over tasks. The inner step
costs one layer's gradient instead of the whole network's, and the meta-gradient still reaches the
body through θ'_head (unless ``first_order``).

This module is the worked example of docs/adding-a-learner.md: the learner is this module (its
class, options and builder) and one entry in :data:`armeta_rl.factory.LEARNERS`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import Tensor, nn
from torch.func import functional_call, grad
from torchrl.modules import MLP

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.fields import Section, above, at_least, each, key, register
from armeta_rl.learners.base import mean_squared_error, sizes
from armeta_rl.learners.maml import MAMLLeader, MamlOptions, sgd_step

Params = dict[str, Tensor]

class BodyHead(nn.Module):
    """The paper's ReLU MLP ``in → hidden… → out`` split in two: a body (every layer but the
    last, with a ReLU after each) and a linear head (the last layer), whose parameters are
    ``head.weight`` and ``head.bias``."""

    def __init__(self, in_features: int, out_features: int, hidden: Sequence[int]) -> None:
        super().__init__()
        hidden = [int(h) for h in hidden]
        self.body = MLP(in_features=int(in_features), out_features=hidden[-1],
                        num_cells=hidden[:-1], activation_class=nn.ReLU, activate_last_layer=True)
        self.head = nn.Linear(hidden[-1], int(out_features))

    def forward(self, x: Tensor) -> Tensor:
        return self.head(self.body(x))


@register("learner.anil")
@dataclass(frozen=True)
class AnilOptions(Section):
    """``learner.anil``: ANIL's keys, their types, ranges and defaults.

    Attributes:
        hidden: the widths of the body the builder makes (every layer but the head).
        inner_lr: γ, the step size of the head's inner SGD steps.
        inner_steps: number of inner steps.
        first_order: drop the second-order terms (treat ∇_{θ_head} L^S as a constant).
        outer_lr: Adam learning rate of the meta-update.
    """

    hidden: list[int] = each(at_least(1), nonempty=True, default=[128, 128, 128])
    inner_lr: float = above(0, default=0.01)
    inner_steps: int = at_least(1, default=1)
    first_order: bool = key(default=False)
    outer_lr: float = above(0, default=0.001)


class ANILLeader(MAMLLeader):
    """ANIL on regression data ``{"support": {"x", "y"}, "query": {"x", "y"}}``, metric MSE.

    Everything but the inner step is :class:`~armeta_rl.learners.maml.MAMLLeader`'s (its batched
    ``vmap`` over tasks, the weighted Adam meta-update, evaluation and checkpoints).

    Args:
        model: the network; its parameters are θ.
        collector: produces support/query data for a batch of tasks.
        options: the keys of ``learner.anil`` (:class:`AnilOptions`).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors import SinusoidCollector
        >>> from armeta_rl.learners import ANILLeader
        >>> from armeta_rl.learners.anil import AnilOptions, BodyHead
        >>> _ = torch.manual_seed(0)
        >>> leader = ANILLeader(BodyHead(1, 1, [16, 16]), SinusoidCollector(20, 50),
        ...                     AnilOptions(inner_lr=0.1))
        >>> data = leader.collect(TensorDict({"params": torch.tensor([[2.0, 0.0]])}, [1]))
        >>> with torch.no_grad():  # θ's query MSE on y = 2 sin x, without adapting
        ...     error = leader.model(data["query", "x"]) - data["query", "y"]
        >>> round(float(error.square().mean()), 2)
        2.37
        >>> round(float(leader.evaluate(data)), 2)  # after the head's step on the 20 support points
        2.13
        >>> theta = dict(leader.model.named_parameters())
        >>> adapted = leader.adapt(theta, data["support", "x"][0], data["support", "y"][0])
        >>> sorted(name for name in theta if not torch.equal(adapted[name], theta[name]))
        ['head.bias', 'head.weight']
    """

    def __init__(
        self, model: BodyHead, collector: TaskCollector, options: AnilOptions = AnilOptions()
    ) -> None:
        # MAML's per-task form, vmapped, with ANIL's inner step (adapt) in it
        super().__init__(model, collector, MamlOptions(**asdict(options), adaptation="vmap"))

    def support_loss(self, head: Params, params: Params, x: Tensor, y: Tensor) -> Tensor:
        """L(D^S; θ_body, head): the mean squared error with the head's parameters ``head``."""
        return mean_squared_error(functional_call(self.model, {**params, **head}, (x,)), y)

    def adapt(self, params: Params, x: Tensor, y: Tensor) -> Params:
        """θ'_τ = (θ_body, θ'_head): ``inner_steps`` SGD steps of the head on one task's support
        set ``(x, y)``; the body is θ's."""
        head = {name: p for name, p in params.items() if name.startswith("head.")}
        for _ in range(self.inner_steps):
            steps = grad(self.support_loss)(head, params, x, y)
            if self.first_order:
                steps = {name: s.detach() for name, s in steps.items()}
            head = sgd_step(head, steps, self.inner_lr)
        return {**params, **head}


def build_anil(options: AnilOptions, collector: TaskCollector, device: torch.device,
               model: Mapping[str, Any]) -> ANILLeader:
    """ANIL with ``options``, its network sized by the collector, on ``device`` (a body and a
    linear head: no choices in ``model``)."""
    network = BodyHead(*sizes(collector), options.hidden).to(device)
    return ANILLeader(network, collector, options)
