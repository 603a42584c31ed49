"""Gaussian MLP policy of MAML-TRPO (MAML paper, Sec. 5.3; pytorch-maml-rl's NormalMLPPolicy).

π_θ(a|s) = N(μ_θ(s), diag(σ²)) with μ an MLP (two hidden layers of 64, tanh) and a
state-independent log σ initialized at 0 (σ = 1). The same network serves two uses:

* as a TorchRL ``ProbabilisticActor`` (``make_actor``), for ``env.rollout`` and collectors;
* functionally, under per-task parameters with a leading task dimension ``K`` (``loc_scale``):
  ``torch.func.functional_call`` vmapped over tasks, so the ``K`` adapted policies of MAML run
  together. Sampling stays outside ``vmap``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModule
from torch import Tensor, nn
from torch.func import functional_call, vmap
from torchrl.modules import MLP, IndependentNormal, ProbabilisticActor

MIN_LOG_STD = math.log(1e-6)


class GaussianMLP(nn.Module):
    """Observation ``[..., obs_dim]`` -> (loc, scale) ``[..., action_dim]`` each.

    Weights use Xavier-uniform and biases zero, as in pytorch-maml-rl; ``log_std`` starts at 0.
    """

    def __init__(
        self, obs_dim: int = 2, action_dim: int = 2, hidden: Sequence[int] = (64, 64)
    ) -> None:
        super().__init__()
        self.mean = MLP(
            in_features=obs_dim,
            out_features=action_dim,
            num_cells=list(hidden),
            activation_class=nn.Tanh,
        )
        for layer in self.mean.modules():
            if isinstance(layer, nn.Linear):
                nn.init.xavier_uniform_(layer.weight)
                nn.init.zeros_(layer.bias)
        self.log_std = nn.Parameter(torch.zeros(action_dim))

    def forward(self, observation: Tensor) -> tuple[Tensor, Tensor]:
        loc = self.mean(observation)
        scale = self.log_std.clamp_min(MIN_LOG_STD).exp().expand_as(loc)
        return loc, scale


def loc_scale(
    net: GaussianMLP, params: TensorDictBase, observation: Tensor
) -> tuple[Tensor, Tensor]:
    """(loc, scale) of π under per-task parameters.

    Args:
        net: the policy network (its own parameters are ignored).
        params: parameters with batch size ``[K]``, one set per task.
        observation: ``[K, ...batch, obs_dim]``; task ``k`` is evaluated with ``params[k]``.
    """
    return loc_scale_flat(net, params.flatten_keys(".").to_dict(), observation)


def loc_scale_flat(
    net: GaussianMLP, params: dict[str, Tensor], observation: Tensor
) -> tuple[Tensor, Tensor]:
    """:func:`loc_scale` with per-task parameters as a flat ``{"a.b": [K, ...]}`` dict."""
    return vmap(lambda p, obs: functional_call(net, p, (obs,)))(params, observation)


class PerTaskLocScale(nn.Module):
    """(loc, scale) for observations ``[K, ...]``: per-task ``params`` ``[K]`` when given, else the
    network's own (shared) parameters."""

    def __init__(self, net: GaussianMLP, params: TensorDictBase | None = None) -> None:
        super().__init__()
        self.net = net
        # flattened once: the module runs at every env step of a rollout
        self.params = None if params is None else params.flatten_keys(".").to_dict()

    def forward(self, observation: Tensor) -> tuple[Tensor, Tensor]:
        if self.params is None:
            return self.net(observation)
        return loc_scale_flat(self.net, self.params, observation)


def make_actor(net: GaussianMLP, params: TensorDictBase | None = None) -> ProbabilisticActor:
    """A TorchRL ``ProbabilisticActor`` reading ``"observation"`` and writing ``"loc"``,
    ``"scale"``, ``"action"`` and ``"action_log_prob"``; with ``params`` ``[K]`` it acts with task
    ``k``'s parameters on batch entries ``[k, ...]``."""
    module = TensorDictModule(
        PerTaskLocScale(net, params), in_keys=["observation"], out_keys=["loc", "scale"]
    )
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        distribution_class=IndependentNormal,
        return_log_prob=True,
        default_interaction_type=InteractionType.RANDOM,
    )


def log_prob(loc: Tensor, scale: Tensor, action: Tensor) -> Tensor:
    """Log-density of a diagonal Gaussian, summed over the action dimension."""
    return torch.distributions.Normal(loc, scale).log_prob(action).sum(-1)


def kl_divergence(loc: Tensor, scale: Tensor, old_loc: Tensor, old_scale: Tensor) -> Tensor:
    """KL(π || π_old) of diagonal Gaussians, summed over the action dimension."""
    new = torch.distributions.Normal(loc, scale)
    old = torch.distributions.Normal(old_loc, old_scale)
    return torch.distributions.kl_divergence(new, old).sum(-1)
