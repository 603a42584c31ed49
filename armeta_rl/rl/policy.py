"""Gaussian MLP policy of MAML-TRPO (MAML paper, Sec. 5.3; pytorch-maml-rl's NormalMLPPolicy).

π_θ(a|s) = N(μ_θ(s), diag(σ²)) with μ an MLP (two hidden layers of 64, tanh) and a
state-independent log σ initialized at 0 (σ = 1). The same network serves two uses:

* as a TorchRL ``ProbabilisticActor`` (``make_actor``), for ``env.rollout`` and collectors;
* functionally, under per-task parameters with a leading task dimension ``K``
  (``loc_scale_flat``):
  the pure :meth:`GaussianMLP.forward_with` vmapped over tasks, so the ``K`` adapted policies of
  MAML run together. Sampling stays outside ``vmap``. Rollouts, which need no gradient, run the
  same function as one batched matrix product per layer (``loc_scale_batched``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModuleBase
from torch import Tensor, nn
from torch.func import vmap
from torch.nn import functional as F
from torchrl.modules import MLP, IndependentNormal, ProbabilisticActor

MIN_LOG_STD = math.log(1e-6)

Linear = Callable[[Tensor, Tensor, Tensor], Tensor]
"""A linear layer as a function of (input, weight, bias), laid out as ``F.linear``'s arguments."""


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

    def forward_with(
        self, params: dict[str, Tensor], observation: Tensor, linear: Linear = F.linear
    ) -> tuple[Tensor, Tensor]:
        """:meth:`forward` with the parameters ``params`` (named as in ``named_parameters``),
        each linear layer applied as ``linear(hidden, weight, bias)``.

        The pure function that ``vmap`` batches over tasks: it walks the MLP's layers with
        ``F.linear`` instead of ``functional_call``, whose per-call swapping of the module's
        tensors costs as much as this small network's arithmetic. :func:`loc_scale_batched`
        runs it on per-task parameters with a per-task ``linear`` instead.
        """
        hidden = observation
        for name, layer in self.mean.named_children():
            if isinstance(layer, nn.Linear):
                weight, bias = params[f"mean.{name}.weight"], params[f"mean.{name}.bias"]
                hidden = linear(hidden, weight, bias)
            else:
                hidden = layer(hidden)
        scale = params["log_std"].clamp_min(MIN_LOG_STD).exp().expand_as(hidden)
        return hidden, scale


def loc_scale_flat(
    net: GaussianMLP, params: dict[str, Tensor], observation: Tensor
) -> tuple[Tensor, Tensor]:
    """(loc, scale) of π under per-task parameters.

    Args:
        net: the policy network (its own parameters are ignored).
        params: one set of parameters per task, as a flat ``{"a.b": [K, ...]}`` dict.
        observation: ``[K, ...batch, obs_dim]``; task ``k`` is evaluated with ``params[k]``.
    """
    return vmap(net.forward_with)(params, observation)


def loc_scale_batched(
    net: GaussianMLP, params: dict[str, Tensor], observation: Tensor
) -> tuple[Tensor, Tensor]:
    """:func:`loc_scale_flat` computed with one ``baddbmm`` over the ``K`` tasks per layer
    instead of ``vmap``, for rollouts: the same values (bit for bit in the point_nav runs checked
    on the development machine, so switching changed no trajectory).

    A rollout runs the policy at every env step on a small batch, where ``vmap``'s per-call
    overhead outweighs the arithmetic: for 20 tasks × 20 episodes it cost about 0.9 ms per step,
    a third of the post-adaptation rollout's time. The differentiable paths keep ``vmap``.
    """
    n_tasks, batch = observation.shape[0], observation.shape[1:-1]
    flat = observation.reshape(n_tasks, -1, observation.shape[-1])
    per_task = {**params, "log_std": params["log_std"].unsqueeze(1)}
    loc, scale = net.forward_with(per_task, flat, linear=_per_task_linear)
    shape = (n_tasks, *batch, loc.shape[-1])
    return loc.reshape(shape), scale.reshape(shape)


def _per_task_linear(hidden: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
    """``F.linear`` with a leading task dimension on all three arguments: one ``baddbmm``."""
    return torch.baddbmm(bias.unsqueeze(1), hidden, weight.transpose(1, 2))


class PerTaskLocScale(TensorDictModuleBase):
    """Writes ``"loc"`` and ``"scale"`` for ``"observation"`` ``[K, ...]``: per-task ``params``
    ``[K]`` when given, else the network's own (shared) parameters.

    A ``TensorDictModuleBase`` that sets its two outputs directly: ``TensorDictModule`` passes every
    output through ``TensorDict.from_any``, whose search for an optional pandas import costs about
    0.3 ms per tensor, and this module runs at every env step of a rollout.
    """

    in_keys = ["observation"]
    out_keys = ["loc", "scale"]

    def __init__(self, net: GaussianMLP, params: TensorDictBase | None = None) -> None:
        super().__init__()
        self.net = net
        # flattened once: the module runs at every env step of a rollout
        self.params = None if params is None else params.flatten_keys(".").to_dict()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation = tensordict.get("observation")
        if self.params is None:
            loc, scale = self.net(observation)
        else:
            loc, scale = loc_scale_batched(self.net, self.params, observation)
        return tensordict.set("loc", loc).set("scale", scale)


def make_actor(net: GaussianMLP, params: TensorDictBase | None = None) -> ProbabilisticActor:
    """A TorchRL ``ProbabilisticActor`` reading ``"observation"`` and writing ``"loc"``,
    ``"scale"``, ``"action"`` and ``"action_log_prob"``; with ``params`` ``[K]`` it acts with task
    ``k``'s parameters on batch entries ``[k, ...]``."""
    return ProbabilisticActor(
        PerTaskLocScale(net, params),
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
