"""MAML-PPO leader: MAML with a PPO outer step, both objectives TorchRL loss modules (the ProMP
family, Rothfuss et al. 2019, without its low-variance inner estimator; learn2learn's
``examples/rl/promp.py`` takes the same two losses).

One meta-iteration on K tasks, batched over tasks, is MAML-TRPO's
(:mod:`armeta_rl.learners.maml_trpo`) up to the outer step:

1. roll out π_θ, take the inner step θ'_k = θ − α ∇_θ L^in_k(θ) with the inner loss module
   (TorchRL's ``A2CLoss`` by default: −log π(a|s)·Â), roll out the adapted policies;
2. ``epochs`` times: retake the inner step from the current θ on the same pre-adaptation
   episodes, score the post-adaptation episodes with the outer loss module (TorchRL's
   ``ClipPPOLoss``: −min(r Â, clip(r, 1 ± ε) Â), r = π_θ'_k(a|s)/π_data(a|s)), and take one Adam
   step on Σ_k w_k L^out_k(θ'_k(θ)), through the inner step (second order unless
   ``first_order``).

The clipped ratio keeps the epochs near the policy that collected the data, the role TRPO's
trust region plays in MAML-TRPO. Both losses run batched over tasks by
:func:`~armeta_rl.rl.losses.per_task_objective`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import LossModule

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.devices import CPU
from armeta_rl.fields import Section, above, at_least, each, inside, key, register
from armeta_rl.learners.base import TaskWeights, weighted_sum
from armeta_rl.learners.maml_trpo import MAMLTRPOLeader, MamlTrpoOptions, MetaBatch, as_task_params
from armeta_rl.rl.losses import (
    check_loss_module,
    clip_ppo_loss,
    per_task_objective,
    reinforce_loss,
)
from armeta_rl.rl.policy import make_actor


@register("learner.maml_ppo")
@dataclass(frozen=True)
class MamlPpoOptions(Section):
    """``learner.maml_ppo``: MAML-PPO on episode benchmarks (point_nav, ant_goal). The policy,
    the inner step and the advantages are MAML-TRPO's (:class:`MamlTrpoOptions`, same defaults);
    the outer step is PPO's.

    Attributes:
        hidden_sizes: hidden layers of the policy MLP.
        inner_lr: inner policy-gradient step size α.
        gamma: discount.
        gae_lambda: GAE λ.
        baseline_reg: ridge coefficient of the linear baseline.
        first_order: drop the second-order terms of the inner step (FO-MAML ablation).
        lr: Adam learning rate of the outer step.
        epochs: outer Adam steps per meta-iteration on the same episodes.
        clip_epsilon: PPO's clipping range ε of the probability ratio.
    """

    hidden_sizes: list[int] = each(at_least(1), default=[64, 64])
    inner_lr: float = above(0, default=0.1)
    gamma: float = inside(0, 1, "(]", default=0.99)
    gae_lambda: float = inside(0, 1, "[]", default=1.0)
    baseline_reg: float = at_least(0, default=1.0e-5)
    first_order: bool = key(default=False)
    lr: float = above(0, default=1.0e-3)
    epochs: int = at_least(1, default=5)
    clip_epsilon: float = above(0, default=0.2)


class MAMLPPOLeader(MAMLTRPOLeader):
    """The meta-RL leader θ (Gaussian MLP policy) trained by MAML-PPO: MAML-TRPO's collection,
    inner step and evaluation, with PPO epochs under Adam as the outer step.

    Args:
        collector: episode collector; its env's observation and action sizes size the policy.
        options: the keys of ``learner.maml_ppo`` (:class:`MamlPpoOptions`).
        device: where the policy and the meta-update computations live.
        inner_loss: builds the inner objective from the policy's actor
            (:func:`~armeta_rl.rl.losses.reinforce_loss` by default).
        outer_loss: builds the outer objective from the policy's actor
            (:func:`~armeta_rl.rl.losses.clip_ppo_loss` with the options' ε by default).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors.episodes import PointNavigationCollector
        >>> from armeta_rl.learners import MAMLPPOLeader
        >>> from armeta_rl.learners.maml_ppo import MamlPpoOptions
        >>> _ = torch.manual_seed(0)
        >>> collector = PointNavigationCollector(episodes=20, max_steps=10)
        >>> options = MamlPpoOptions(hidden_sizes=[8], inner_lr=0.5, epochs=5)
        >>> leader = MAMLPPOLeader(collector, options)
        >>> goals = torch.tensor([[0.5, 0.5], [-0.5, 0.5], [0.5, -0.5]])
        >>> data = leader.collect(TensorDict({"params": goals}, [3]))
        >>> leader.evaluate_before(data), leader.evaluate(data)  # -return, then after adapting
        (tensor([6.9240, 6.9703, 7.2893]), tensor([5.8232, 6.0165, 6.5115]))
        >>> _, stats = leader.step(data, weights=lambda losses: torch.full((3,), 1 / 3))
        >>> # the first epoch's ratio is 1 and the normalized advantages average 0
        >>> abs(round(stats["ppo_objective_first"], 4)), round(stats["ppo_objective_last"], 4)
        (0.0, -0.0062)
    """

    def __init__(
        self,
        collector: TaskCollector,
        options: MamlPpoOptions = MamlPpoOptions(),
        device: torch.device = CPU,
        inner_loss: Callable[[ProbabilisticActor], LossModule] = reinforce_loss,
        outer_loss: Callable[[ProbabilisticActor], LossModule] | None = None,
    ) -> None:
        shared = MamlTrpoOptions(
            hidden_sizes=options.hidden_sizes, inner_lr=options.inner_lr, gamma=options.gamma,
            gae_lambda=options.gae_lambda, baseline_reg=options.baseline_reg,
            first_order=options.first_order,
        )
        super().__init__(collector, shared, device, inner_loss)
        if outer_loss is None:
            outer_loss = partial(clip_ppo_loss, clip_epsilon=options.clip_epsilon)
        self.outer_objective = check_loss_module(outer_loss(make_actor(self.net)), self.net)
        self.epochs = int(options.epochs)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=options.lr)

    def collect(self, tasks: TensorDictBase, collector: TaskCollector | None = None,
                create_graph: bool = False) -> MetaBatch:
        """MAML-TRPO's collection, keeping no graph: every epoch of :meth:`step` retakes the
        inner step from the θ it starts from."""
        return super().collect(tasks, collector, create_graph=False)

    def outer_loss(self, batch: MetaBatch) -> torch.Tensor:
        """Per-task outer loss ``[K]`` at the current θ: the inner step retaken from θ on the
        pre-adaptation episodes, then the outer loss module on the adapted policies'
        episodes."""
        adapted = self.adapt(self.theta(), batch.train, batch.train_advantages,
                             create_graph=True)
        return per_task_objective(self.outer_objective, self.net, as_task_params(adapted),
                                  batch.valid, batch.valid_advantages)

    def step(
        self, batch: MetaBatch, weights: TaskWeights
    ) -> tuple[TensorDict, dict[str, float]]:
        """Score the episodes of :meth:`collect` before and after adaptation, then ``epochs``
        Adam steps on Σ_k w_k L^out_k with ``w = weights(losses)``.

        Returns the per-task scores of :meth:`~MAMLTRPOLeader.scores` (``"loss"``, the
        returns before and after adaptation and their gain) and ``"ppo_objective_first"`` /
        ``"ppo_objective_last"``: the weighted outer loss of the first and the last epoch,
        before its step.
        """
        per_task = self.scores(batch)
        w = weights(per_task["loss"]).to(batch.valid["reward"].dtype)
        objectives = []
        for _ in range(self.epochs):
            objective = weighted_sum(w, self.outer_loss(batch))
            self.optimizer.zero_grad(set_to_none=True)
            objective.backward()
            self.optimizer.step()
            objectives.append(objective.item())
        return per_task, {"ppo_objective_first": objectives[0],
                          "ppo_objective_last": objectives[-1]}

    def state_dict(self) -> dict[str, Any]:
        return {"policy": self.net.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.net.load_state_dict(state["policy"])
        self.optimizer.load_state_dict(state["optimizer"])


def build_maml_ppo(options: MamlPpoOptions, collector: TaskCollector, device: torch.device,
                   model: Mapping[str, Any]) -> MAMLPPOLeader:
    """MAML-PPO with ``options``, its policy sized by the collector's env, on ``device`` (a
    Gaussian MLP policy: no choices in ``model``)."""
    return MAMLPPOLeader(collector, options, device)
