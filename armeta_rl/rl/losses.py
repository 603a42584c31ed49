"""TorchRL ``LossModule``s as the per-task objectives of meta-RL, batched over tasks.

A meta-RL learner adapts one parameter set per task, θ'_k, and scores task k's episodes under
θ'_k. :func:`per_task_objective` evaluates any TorchRL loss that way: the loss module is built
once, non-functional (``functional=False``), on an actor wrapping the leader's policy network,
and ``torch.vmap`` runs it over the task dimension with task k's parameters in place of the
network's (``torch.func.functional_call``), so the K losses are one batched call, differentiable
in the parameters (and, through the inner step, in θ). The loss's per-step values
(``reduction="none"``) become per-task values with :func:`~armeta_rl.rl.baseline.episode_mean`
over each task's valid steps, as MAML-TRPO's surrogate weighs them.

The advantages are the data's own (the per-task linear baseline's normalized GAE,
:func:`~armeta_rl.rl.baseline.gae_advantages`), passed under the loss's ``advantage`` key, so no
critic is trained (TorchRL's ``A2CLoss`` still takes a critic network when built:
:func:`advantage_critic` is the stand-in, never called).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import Tensor, nn
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import A2CLoss, ClipPPOLoss, LossModule

from armeta_rl.rl.baseline import episode_mean

ADVANTAGE_KEY = "advantage"
"""Key of the advantages ``[K, E, T, 1]`` in the data a loss module reads."""


def advantage_critic() -> TensorDictModule:
    """The critic ``A2CLoss`` is built with when the advantages come with the data: it copies
    the data's ``"state_value"`` and is never called (no critic coefficient, and the advantages
    are in the data)."""
    return TensorDictModule(nn.Identity(), in_keys=["state_value"], out_keys=["state_value"])


def reinforce_loss(actor: ProbabilisticActor) -> A2CLoss:
    """The inner objective of MAML (Finn et al. 2017, Sec. 5.3): −log π(a|s)·Â per step,
    TorchRL's ``A2CLoss`` with the data's advantages, no critic term and no entropy bonus."""
    loss = A2CLoss(actor, advantage_critic(), entropy_bonus=False, critic_coeff=None,
                   functional=False, reduction="none")
    loss.set_keys(sample_log_prob="log_prob", advantage=ADVANTAGE_KEY)
    return loss


def clip_ppo_loss(actor: ProbabilisticActor, clip_epsilon: float = 0.2) -> ClipPPOLoss:
    """PPO's clipped surrogate (Schulman et al. 2017, Eq. (7)) per step,
    −min(r Â, clip(r, 1 − ε, 1 + ε) Â) with r = π(a|s)/π_data(a|s) (the data's ``"log_prob"``),
    TorchRL's ``ClipPPOLoss`` without a critic and without its entropy bonus (which checks its
    values with data-dependent control flow, so it cannot run under ``vmap``)."""
    loss = ClipPPOLoss(actor, None, clip_epsilon=clip_epsilon, entropy_bonus=False,
                       critic_coeff=None, functional=False, reduction="none")
    loss.set_keys(sample_log_prob="log_prob", advantage=ADVANTAGE_KEY)
    return loss


def check_loss_module(loss: LossModule, net: nn.Module) -> LossModule:
    """``loss`` if :func:`per_task_objective` can batch it over tasks with ``net``'s parameters:
    built with ``functional=False`` (a functional loss swaps its own copy of the parameters in at
    every call) on an actor whose parameters are ``net``'s; ``ValueError`` otherwise."""
    if getattr(loss, "functional", True):
        raise ValueError(f"{type(loss).__name__} must be built with functional=False: it is "
                         "called with each task's parameters in place of the policy network's")
    actor_params = {id(p) for p in loss.actor_network.parameters()}
    if not actor_params or actor_params != {id(p) for p in net.parameters()}:
        raise ValueError(f"{type(loss).__name__}'s actor must be built on the leader's policy "
                         "network (make_actor(leader.net)), whose parameters it adapts per task")
    return loss


class LossCall(nn.Module):
    """A loss module called through a plain ``nn.Module``: ``torch.func.functional_call`` lists
    a module's parameters with ``named_parameters(remove_duplicate=False)``, which
    ``LossModule.named_parameters`` does not take, so the call goes through this wrapper, whose
    parameters are the loss's under ``"loss."``."""

    def __init__(self, loss: LossModule) -> None:
        super().__init__()
        self.loss = loss

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.loss(tensordict)


def parameter_names(call: nn.Module, net: nn.Module) -> dict[str, str]:
    """For each of ``net``'s parameters, its name inside ``call`` (which reaches the network
    through a loss module and its actor, under a longer name): ``{name in net: name in call}``."""
    inside = {id(p): name for name, p in call.named_parameters(remove_duplicate=False)}
    return {name: inside[id(p)] for name, p in net.named_parameters()}


def per_task_objective(
    loss: LossModule, net: nn.Module, params: TensorDictBase, data: TensorDictBase,
    advantages: Tensor,
) -> Tensor:
    """The loss of every task under its own parameters, ``[K]``.

    Args:
        loss: a non-functional TorchRL loss module whose actor acts with ``net``
            (:func:`check_loss_module`), with ``reduction="none"``.
        net: the policy network; task k's parameters are swapped into it for task k.
        params: per-task parameters ``[K]``, named as ``net``'s (a nested TensorDict).
        data: episodes ``[K, E, T]`` with the loss's in-keys and a bool ``"mask"`` of valid steps.
        advantages: ``[K, E, T]``, written under :data:`ADVANTAGE_KEY` for the loss.

    Returns:
        The :func:`episode_mean` of the loss's per-step ``"loss_objective"`` over each task's
        valid steps.
    """
    batch = data.clone(False).set(ADVANTAGE_KEY, advantages.unsqueeze(-1))
    call = LossCall(loss)
    names = parameter_names(call, net)
    flat = params.flatten_keys(".")
    swapped = {names[name]: flat.get(name) for name in names}

    def task_loss(task_params: dict[str, Tensor], task_data: TensorDictBase) -> Tensor:
        out = torch.func.functional_call(call, task_params, (task_data,))
        return out.get("loss_objective")

    per_step = torch.vmap(task_loss, randomness="different")(swapped, batch)
    return episode_mean(per_step, data.get("mask"))
