"""Conditional neural process leader (Garnelo et al. 2018; paper, Example AR-CNP, Eq. (8), and
Algorithm 2).

θ = {θ_1, θ_2}: a set encoder h_{θ_1} maps the support set to a representation
z = mean_i h_{θ_1}(x_i, y_i), and a decoder g_{θ_2}(z, x) predicts a Gaussian over y at each query
point. Adaptation is this forward pass alone: Algorithm 2 has no inner gradient step, so the leader
update is one Adam step on Σ_k w_k L(D^Q_{τ_k}; z_k, θ_2) for the whole task batch.

Architecture (paper, appendix "Neural Architectures & Optimization"): the encoder is a three-layer
MLP with 128 hidden units and a 128-d output, the representations are averaged over the support
set, and the decoder is a two-layer MLP on (z, x_query); ReLU activations, Adam with lr 1e-3.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor, nn
from torch.nn import functional as F
from torchrl.modules import MLP

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.devices import CPU
from armeta_rl.errors import ConfigError
from armeta_rl.fields import Section, above, at_least, one_of, register
from armeta_rl.learners.base import (
    OneNetworkLeader,
    TaskWeights,
    mean_squared_error,
    sizes,
)

MIN_STD = 0.1


class ConditionalNeuralProcess(nn.Module):
    """Encoder–mean–decoder network; every tensor may carry any leading batch shape ``[*B]``.

    The predictive standard deviation is σ = 0.1 + 0.9·softplus(s) for the decoder's raw output s
    (Le et al. 2018, "Empirical evaluation of neural process objectives"): the 0.1 floor keeps the
    Gaussian likelihood from collapsing onto single points early in training.
    """

    def __init__(self, in_features: int, out_features: int, hidden: int = 128) -> None:
        super().__init__()
        self.encoder = MLP(in_features=in_features + out_features, out_features=hidden,
                           num_cells=[hidden, hidden], activation_class=nn.ReLU)
        self.decoder = MLP(in_features=hidden + in_features, out_features=2 * out_features,
                           num_cells=[hidden], activation_class=nn.ReLU)

    def represent(self, support_x: Tensor, support_y: Tensor) -> Tensor:
        """z = h_{θ_1}(D^S) of paper Eq. (8): the mean over the support points of the encoder's
        h(x, y), ``[*B, S, ·]`` → ``[*B, hidden]``."""
        return self.encoder(torch.cat([support_x, support_y], -1)).mean(-2)

    def forward(self, support_x: Tensor, support_y: Tensor,
                query_x: Tensor) -> tuple[Tensor, Tensor]:
        """Predictive mean and standard deviation ``[*B, Q, out]`` at the query inputs."""
        z = self.represent(support_x, support_y)
        z = z.unsqueeze(-2).expand(*query_x.shape[:-1], z.shape[-1])
        mean, raw_std = self.decoder(torch.cat([z, query_x], -1)).chunk(2, -1)
        return mean, MIN_STD + (1.0 - MIN_STD) * F.softplus(raw_std)


def gaussian_nll(mean: Tensor, std: Tensor, target: Tensor) -> Tensor:
    """Elementwise −ln N(target; mean, std²), including the ½·ln 2π constant."""
    return F.gaussian_nll_loss(mean, target, std.square(), full=True, reduction="none")


@register("learner.cnp")
@dataclass(frozen=True)
class CnpOptions(Section):
    """``learner.cnp``: the CNP's keys, their types, ranges and defaults (encoder 3 × ``hidden``
    → mean over the support set → decoder ``hidden`` → (μ, σ)).

    Attributes:
        lr: Adam learning rate (1e-3 in the paper).
        hidden: width of every hidden layer and of the representation z (128 in the paper).
        likelihood: training loss per task, averaged over query points and output dimensions:
            ``"gaussian"`` (negative log-likelihood of the predicted Gaussian, as in Garnelo et al.)
            or ``"mse"`` (squared error of the predicted mean; the std head is then unused).
    """

    lr: float = above(0, default=0.001)
    hidden: int = at_least(1, default=128)
    likelihood: str = one_of("gaussian", "mse", default="gaussian")  # Gaussian NLL (paper) or mse


class CNPLeader(OneNetworkLeader):
    """The CNP as a leader: collect support/query data, predict, score, one Adam step.

    Args:
        in_features: dimension of the inputs x.
        out_features: dimension of the targets y.
        collector: returns ``{"support": {"x", "y"}, "query": {"x", "y"}}`` with batch ``[K]``.
        options: the keys of ``learner.cnp`` (:class:`CnpOptions`).
        device: where the network and Adam's state live (its initial weights are drawn on the
            CPU, so a seed gives the same network on every device).

    :meth:`evaluate` always reports the mean squared error of the predicted mean (``metric="mse"``),
    like MAML, whichever likelihood trains the network.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors import SinusoidCollector
        >>> from armeta_rl.learners import CNPLeader
        >>> from armeta_rl.learners.cnp import CnpOptions
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> _ = torch.manual_seed(0)
        >>> options = CnpOptions(hidden=32, lr=0.01, likelihood="mse")
        >>> leader = CNPLeader(1, 1, SinusoidCollector(20, 50), options)
        >>> space = TaskSpace(["amplitude", "phase"], low=[0.1, 0.0], high=[5.0, 3.1416])
        >>> for _ in range(300):  # 300 steps of 8 sinusoids from p0
        ...     data = leader.collect(BoxUniform(space).sample(8))
        ...     _ = leader.step(data, weights=lambda losses: torch.full_like(losses, 1 / 8))
        >>> tasks = torch.tensor([[4.0, 0.0], [4.0, 3.1416]])  # y = 4 sin x and y = -4 sin x
        >>> data = leader.collect(TensorDict({"params": tasks}, [2]))
        >>> leader.evaluate(data).round(decimals=1)  # each conditioned on its own support set
        tensor([5.6000, 4.7000])
        >>> data["support"] = data["support"].flip(0)  # on the other task's: the sign is wrong
        >>> leader.evaluate(data).round(decimals=1)
        tensor([16.5000, 15.0000])
    """

    metric = "mse"

    def __init__(self, in_features: int, out_features: int, collector: TaskCollector,
                 options: CnpOptions = CnpOptions(),
                 device: torch.device = CPU) -> None:
        self.collector = collector
        self.likelihood = options.likelihood
        self.model = ConditionalNeuralProcess(in_features, out_features, options.hidden).to(device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=options.lr)

    def predict(self, data: TensorDict) -> tuple[Tensor, Tensor]:
        """Predictive mean and std ``[K, Q, out]`` at the query inputs of ``data``."""
        return self.model(data["support", "x"], data["support", "y"], data["query", "x"])

    def task_losses(self, data: TensorDict) -> tuple[Tensor, Tensor]:
        """Per-task training loss L(D^Q_τ; z, θ_2) of paper Eq. (8) ``[K]`` (the chosen likelihood)
        and query MSE ``[K]``."""
        mean, std = self.predict(data)
        target = data["query", "y"]
        squared_error = mean_squared_error(mean, target, (-2, -1))
        if self.likelihood == "mse":
            return squared_error, squared_error
        return gaussian_nll(mean, std, target).mean((-2, -1)), squared_error

    def step(self, data: TensorDict, weights: TaskWeights) -> tuple[TensorDict, dict[str, float]]:
        """One Adam step on Σ_k w_k L_k with ``w = weights(L.detach())`` (Algorithm 2) on the
        support/query ``data`` ``[K]``.

        Returns a TensorDict ``[K]`` with the detached per-task ``"loss"`` and query ``"mse"``,
        both before the update, and no scalars.
        """
        losses, squared_error = self.task_losses(data)
        self.descend(losses, weights)
        return TensorDict({"loss": losses.detach(), "mse": squared_error.detach()},
                          batch_size=data.batch_size), {}

    @torch.no_grad()
    def evaluate(self, data: TensorDict) -> Tensor:
        """Per-task query MSE ``[K]`` of the predicted mean on ``data`` at the current θ."""
        mean, _ = self.predict(data)
        return mean_squared_error(mean, data["query", "y"], (-2, -1))


def build_cnp(options: CnpOptions, collector: TaskCollector, device: torch.device,
              model: Mapping[str, Any]) -> CNPLeader:
    """The CNP with ``options``, sized by the collector, on ``device`` (it has no heads to choose
    in ``model``)."""
    head = model.get("head", "none")
    if head != "none":
        raise ConfigError("benchmark.model.head", head, "the CNP leader has no heads: use none")
    return CNPLeader(*sizes(collector), collector, options, device=device)
