"""Gaussian MLP policy of MAML-TRPO (MAML paper, Sec. 5.3; pytorch-maml-rl's NormalMLPPolicy).

π_θ(a|s) = N(μ_θ(s), diag(σ²)) with μ an MLP (two hidden layers of 64, tanh) and a
state-independent log σ initialized at 0 (σ = 1). The same network serves three uses:

* as a TorchRL ``ProbabilisticActor`` (``make_actor``), for ``env.rollout`` and TorchRL's losses;
* functionally, under per-task parameters with a leading task dimension ``K`` (``loc_scale``):
  each layer one batched product over tasks, so the ``K`` adapted policies of MAML run together,
  in rollouts and in the differentiable losses alike;
* as :class:`GaussianActor`, the collectors' actor: the ``ProbabilisticActor``'s draws and
  outputs, without its per-call distribution machinery, which costs more than this network at
  every env step of a rollout.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModuleBase
from torch import Tensor, nn
from torch.nn import functional as F
from torchrl.modules import MLP, IndependentNormal, ProbabilisticActor

MIN_LOG_STD = math.log(1e-6)


class GaussianMLP(nn.Module):
    """Observation ``[..., obs_dim]`` -> (loc, scale) ``[..., action_dim]`` each.

    Weights use Xavier-uniform and biases zero, as in pytorch-maml-rl; ``log_std`` starts at 0.

    Examples:
        >>> import torch
        >>> from armeta_rl.rl import GaussianMLP
        >>> net = GaussianMLP(obs_dim=2, action_dim=2, hidden=(16, 16))
        >>> loc, scale = net(torch.zeros(5, 2))
        >>> loc.shape, scale[0]  # log_std starts at 0
        (torch.Size([5, 2]), tensor([1., 1.], grad_fn=<SelectBackward0>))
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
        return self.forward_with(dict(self.named_parameters()), observation)

    def forward_with(self, params: dict[str, Tensor], observation: Tensor
                     ) -> tuple[Tensor, Tensor]:
        """:meth:`forward` with the parameters ``params`` (named as in ``named_parameters``), as
        arguments: what a CUDA graph of a rollout reads (:func:`act`)."""
        hidden = observation
        for name, layer in self.mean.named_children():
            if isinstance(layer, nn.Linear):
                weight, bias = params[f"mean.{name}.weight"], params[f"mean.{name}.bias"]
                hidden = F.linear(hidden, weight, bias)
            else:
                hidden = layer(hidden)
        scale = params["log_std"].clamp_min(MIN_LOG_STD).exp().expand_as(hidden)
        return hidden, scale


def loc_scale(
    net: GaussianMLP, params: dict[str, Tensor], observation: Tensor
) -> tuple[Tensor, Tensor]:
    """(loc, scale) of π under per-task parameters: task ``k``'s :meth:`GaussianMLP.forward`
    with ``params[k]``, every layer one batched product ``x Wₖᵀ + bₖ`` over the tasks (per-call
    overhead, not arithmetic, is what this small network costs, in rollouts and under double
    backward alike).

    Args:
        net: the policy network (its own parameters are ignored).
        params: per-task parameters as a flat ``{"mean.0.weight": [K, ...], ...}`` dict, named as
            in ``net.named_parameters()``.
        observation: ``[K, ...batch, obs_dim]``; task ``k`` is evaluated with ``params[k]``.
    """
    hidden = observation.reshape(observation.shape[0], -1, observation.shape[-1])
    for name, layer in net.mean.named_children():
        if isinstance(layer, nn.Linear):
            weight, bias = params[f"mean.{name}.weight"], params[f"mean.{name}.bias"]
            hidden = torch.matmul(hidden, weight.transpose(-1, -2)) + bias.unsqueeze(-2)
        else:
            hidden = layer(hidden)
    loc = hidden.reshape(*observation.shape[:-1], hidden.shape[-1])
    log_std = params["log_std"].clamp_min(MIN_LOG_STD)
    scale = log_std.exp().reshape(log_std.shape[0], *[1] * (loc.dim() - 2), -1).expand_as(loc)
    return loc, scale


class PerTaskLocScale(TensorDictModuleBase):
    """Writes ``"loc"`` and ``"scale"`` for ``"observation"`` ``[K, ...]``: per-task ``params``
    ``[K]`` when given, else the network's own (shared) parameters.

    A ``TensorDictModuleBase`` that sets its two outputs directly: ``TensorDictModule`` passes every
    output through ``TensorDict.from_any``, whose search for an optional pandas import costs more
    than this small network, and this module runs at every env step of a rollout.
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
            loc, scale = loc_scale(self.net, self.params, observation)
        return tensordict.set("loc", loc).set("scale", scale)


def make_actor(net: GaussianMLP, params: TensorDictBase | None = None) -> ProbabilisticActor:
    """A TorchRL ``ProbabilisticActor`` reading ``"observation"`` and writing ``"loc"``,
    ``"scale"``, ``"action"`` and ``"action_log_prob"``; with ``params`` ``[K]`` it acts with task
    ``k``'s parameters on batch entries ``[k, ...]``.

    Examples:
        >>> import math
        >>> import torch
        >>> from armeta_rl.envs import PointNavigationEnv
        >>> from armeta_rl.rl import GaussianMLP, make_actor
        >>> _ = torch.manual_seed(0)
        >>> actor = make_actor(GaussianMLP(obs_dim=2, action_dim=2))
        >>> first = PointNavigationEnv(batch_size=(1,), seed=0).rollout(1, policy=actor)
        >>> first = first[:, 0].detach()  # the first step
        >>> first["observation"], first["loc"], first["scale"]  # at (0, 0): zero biases, σ = 1
        (tensor([[0., 0.]]), tensor([[0., 0.]]), tensor([[1., 1.]]))
        >>> first["action"]  # a draw of N(0, I)
        tensor([[-0.7086, -0.3113]])
        >>> first["action_log_prob"]  # ln N(a; 0, I) = -‖a‖²/2 - ln 2π
        tensor([-2.1374])
        >>> round(-first["action"].square().sum().item() / 2 - math.log(2 * math.pi), 4)
        -2.1374
    """
    return ProbabilisticActor(
        PerTaskLocScale(net, params),
        in_keys=["loc", "scale"],
        distribution_class=IndependentNormal,
        return_log_prob=True,
        default_interaction_type=InteractionType.RANDOM,
    )


LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))
"""ln √(2π), the normal density's constant, computed as ``torch.distributions.Normal`` does."""


def draw(net: GaussianMLP, params: dict[str, Tensor], observation: Tensor, per_task: bool
         ) -> tuple[Tensor, Tensor, Tensor]:
    """π's (loc, scale) at ``observation`` and an action drawn as ``torch.distributions.Normal``'s
    ``rsample`` draws it, ``loc + ε · scale`` with ε from torch's RNG, under per-task ``params``
    ``[K]`` (``per_task``, :func:`loc_scale`) or one set of parameters for all
    (:meth:`GaussianMLP.forward_with`)."""
    loc, scale = (loc_scale(net, params, observation) if per_task
                  else net.forward_with(params, observation))
    noise = torch.empty(loc.shape, dtype=loc.dtype, device=loc.device).normal_()
    return loc, scale, loc + noise * scale


def action_log_density(loc: Tensor, scale: Tensor, action: Tensor, log_scale: Tensor
                       ) -> Tensor:
    """ln π(a|s) of a diagonal Gaussian, summed over the action dimension:
    ``torch.distributions.Normal``'s ``log_prob`` written out, the same operations in the same
    order, with ``log_scale`` = ``scale.log()`` given (a rollout's is the same at every step)."""
    return (-((action - loc) ** 2) / (2 * scale**2) - log_scale - LOG_SQRT_2PI).sum(-1)


def act(net: GaussianMLP, params: dict[str, Tensor], observation: Tensor, per_task: bool
        ) -> dict[str, Tensor]:
    """π's outputs at ``observation``, acting at random: ``"loc"``, ``"scale"``, ``"action"``
    (:func:`draw`) and ``"action_log_prob"`` (:func:`action_log_density`).

    The draw and the log-density are ``torch.distributions.Normal``'s ``rsample`` and
    ``log_prob`` written out, the same operations in the same order (the same values bit for
    bit, ``tests/test_maml_trpo.py``), without building a distribution object at every env step
    of a rollout, which costs more than the arithmetic."""
    loc, scale, action = draw(net, params, observation, per_task)
    return {"loc": loc, "scale": scale, "action": action,
            "action_log_prob": action_log_density(loc, scale, action, scale.log())}


class GaussianActor(PerTaskLocScale):
    """:func:`make_actor`'s ``ProbabilisticActor`` acting at random, written out (:func:`act`):
    it reads ``"observation"`` and writes ``"loc"``, ``"scale"``, ``"action"`` and
    ``"action_log_prob"``, the same values from the same draws (``tests/test_maml_trpo.py``),
    without the actor's per-call distribution machinery, which costs more than this network at
    each env step of a rollout. It acts at random whatever the exploration type, as a collector's
    actor should. Its network and parameters are held as :class:`PerTaskLocScale` holds them.
    """

    out_keys = ["loc", "scale", "action", "action_log_prob"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        per_task = self.params is not None
        params = self.params if per_task else dict(self.net.named_parameters())
        return tensordict.update(act(self.net, params, tensordict.get("observation"), per_task))


def log_prob(loc: Tensor, scale: Tensor, action: Tensor) -> Tensor:
    """Log-density of a diagonal Gaussian, summed over the action dimension."""
    return torch.distributions.Normal(loc, scale).log_prob(action).sum(-1)


def kl_divergence(loc: Tensor, scale: Tensor, old_loc: Tensor, old_scale: Tensor) -> Tensor:
    """KL(π || π_old) of diagonal Gaussians, summed over the action dimension."""
    new = torch.distributions.Normal(loc, scale)
    old = torch.distributions.Normal(old_loc, old_scale)
    return torch.distributions.kl_divergence(new, old).sum(-1)
