"""MAML-TRPO leader (Finn et al. 2017, Alg. 3 with TRPO as the outer optimizer, Sec. 5.3; the
paper's meta-RL benchmark, appendix "Meta Learning Continuous Control"; pytorch-maml-rl).

One meta-iteration on K tasks, all batched over tasks:

1. roll out π_θ for ``episodes`` episodes per task (one env call, batch ``[K, episodes]``);
2. inner step per task: θ'_k = θ − α ∇_θ L^in_k(θ), L^in_k = −mean(log π_θ(a|s)·Â) with normalized
   GAE advantages from the per-task linear baseline, TorchRL's ``A2CLoss`` batched over tasks
   (:func:`~armeta_rl.rl.losses.per_task_objective`; any loss module built on the policy may take
   its place); the K adapted parameter sets live in a TensorDict ``[K]`` and the adapted
   policies roll out together;
3. outer TRPO step on the weighted post-adaptation surrogate
   Σ_k w_k L^out_k(θ), L^out_k = −mean(π_θ'_k(a|s)/π_old(a|s)·Â), subject to
   Σ_k w_k KL_k(π_θ'_k ‖ π_old) ≤ δ, with w = weights(per-task losses) (ERM: 1/K; the risk
   principles of the paper reweight tasks here). The Hessian-vector products of the KL are taken
   through the inner step (second order).

The per-task loss reported to the game is −(mean return of the adapted policy).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import LossModule

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.collectors.episodes import episode_returns
from armeta_rl.devices import CPU
from armeta_rl.fields import Section, above, at_least, each, inside, key, register
from armeta_rl.learners.base import TaskWeights, weighted_sum
from armeta_rl.learners.maml import sgd_step
from armeta_rl.rl.baseline import gae_advantages
from armeta_rl.rl.losses import check_loss_module, per_task_objective, reinforce_loss
from armeta_rl.rl.policy import GaussianMLP, loc_scale, log_prob, make_actor
from armeta_rl.rl.trpo import (
    backtracking_line_search,
    flatten,
    mean_kl,
    meta_kl_hessian_vector_product,
    surrogate_loss,
    trust_region_step,
    unflatten,
)
from armeta_rl.tasks.protocol import FORWARD_REWARD, TASK_KEY

Params = dict[str, Tensor]


@dataclass
class MetaBatch:
    """One meta-iteration's data: pre-adaptation episodes ``train`` ``[K, E, T]`` and their
    advantages, θ broadcast to ``[K]`` and the adapted parameters ``[K]`` computed from it (with
    their graph to θ when built for an update), and the adapted policies' episodes ``valid`` with
    their advantages."""

    train: TensorDictBase
    train_advantages: Tensor
    broadcast: Params
    adapted: Params
    valid: TensorDictBase
    valid_advantages: Tensor


def as_task_params(params: Params) -> TensorDict:
    """Flat ``{"a.b": [K, ...]}`` parameters as a nested TensorDict ``[K]``."""
    n_tasks = next(iter(params.values())).shape[0]
    return TensorDict(params, batch_size=[n_tasks]).unflatten_keys(".")


class SurrogateGraph(NamedTuple):
    """The adapted parameters θ'_k as detached leaves ``[K, ...]`` and the adapted policies'
    (loc, scale) on the post-adaptation episodes computed from them, graph kept."""

    leaves: list[Tensor]
    outputs: tuple[Tensor, Tensor]


@register("learner.maml_trpo")
@dataclass(frozen=True)
class MamlTrpoOptions(Section):
    """``learner.maml_trpo``: MAML's form on episode benchmarks (point_nav, ant_goal), MAML-TRPO
    with pytorch-maml-rl's settings: its keys, their types, ranges and defaults. The policy's
    input and output sizes are the env's observation and action.

    Attributes:
        hidden_sizes: hidden layers of the policy MLP.
        inner_lr: inner policy-gradient step size α.
        gamma, gae_lambda: discount and GAE λ.
        max_kl: TRPO trust region δ.
        cg_iterations, cg_damping: conjugate-gradient iterations and damping.
        ls_max_steps, ls_backtrack_ratio: backtracking line search.
        baseline_reg: ridge coefficient of the linear baseline.
        first_order: drop the second-order terms of the inner step (FO-MAML ablation).
        hvp_episodes: episodes per task on which the KL's Hessian-vector products are computed
            (``None``: all, the exact MAML-TRPO). Episodes are i.i.d., so the first ``n`` are a
            random subsample; TRPO (Schulman et al. 2015) likewise computes its Fisher-vector
            products on a fraction of the batch to cut the cost of conjugate gradient. The
            products retake the inner step on the first ``n`` training episodes, so the inner
            step's Jacobian is estimated from the subsample too (it is most of their cost). The
            surrogate, its gradient and the line search always use every episode.
    """

    # Gaussian MLP, tanh, state-independent log-std (init 0)
    hidden_sizes: list[int] = each(at_least(1), default=[64, 64])
    inner_lr: float = above(0, default=0.1)
    gamma: float = inside(0, 1, "(]", default=0.99)
    gae_lambda: float = inside(0, 1, "[]", default=1.0)
    max_kl: float = above(0, default=0.01)
    cg_iterations: int = at_least(1, default=10)
    cg_damping: float = at_least(0, default=1.0e-5)
    ls_max_steps: int = at_least(1, default=15)
    ls_backtrack_ratio: float = inside(0, 1, default=0.8)
    baseline_reg: float = at_least(0, default=1.0e-5)
    first_order: bool = key(default=False)
    # None: exact KL Hessian-vector products on all episodes; n: on the first n episodes per task
    # (≈ 20/n times cheaper conjugate gradient)
    hvp_episodes: int | None = at_least(1, default=None)


class MAMLTRPOLeader:
    """The meta-RL leader θ (Gaussian MLP policy) trained by MAML-TRPO.

    Args:
        collector: episode collector (e.g. ``PointNavigationCollector``); it is called as
            ``collect(tasks, policy_params, policy=net)``, and its env's observation and action
            sizes (``in_features``, ``out_features``) size the policy.
        options: the keys of ``learner.maml_trpo`` (:class:`MamlTrpoOptions`).
        device: where the policy and every meta-update computation live (its initial weights are
            drawn on the CPU, so a seed gives the same policy on every device); the collector
            rolls it out on its env's device.
        inner_loss: builds the inner objective, a TorchRL loss module, from the policy's actor
            (:func:`~armeta_rl.rl.losses.reinforce_loss`, TorchRL's ``A2CLoss``, by default; see
            :func:`~armeta_rl.rl.losses.check_loss_module` for what it must be).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors.episodes import PointNavigationCollector
        >>> from armeta_rl.learners import MAMLTRPOLeader
        >>> from armeta_rl.learners.maml_trpo import MamlTrpoOptions
        >>> _ = torch.manual_seed(0)
        >>> collector = PointNavigationCollector(episodes=20, max_steps=10)
        >>> options = MamlTrpoOptions(hidden_sizes=[8], inner_lr=0.5, max_kl=0.01)
        >>> leader = MAMLTRPOLeader(collector, options)
        >>> goals = torch.tensor([[0.5, 0.5], [-0.5, 0.5], [0.5, -0.5]])
        >>> data = leader.collect(TensorDict({"params": goals}, [3]), create_graph=True)
        >>> per_task, stats = leader.step(data, weights=lambda losses: torch.full((3,), 1 / 3))
        >>> per_task["return_pre"], per_task["return_post"]  # one inner step on 20 episodes
        (tensor([-6.9240, -6.9703, -7.2893]), tensor([-5.8232, -6.0165, -6.5115]))
        >>> leader.metric, round(stats["trpo_kl"], 4)  # the loss is -return_post; KL ≤ δ
        ('return', 0.0063)
    """

    metric = "return"
    on_policy = True
    inner_steps = 1
    """The inner steps it adapts with in training (MAML-TRPO's one)."""

    def __init__(
        self,
        collector: TaskCollector,
        options: MamlTrpoOptions = MamlTrpoOptions(),
        device: torch.device = CPU,
        inner_loss: Callable[[ProbabilisticActor], LossModule] = reinforce_loss,
    ) -> None:
        self.collector = collector
        self.net = GaussianMLP(int(collector.in_features), int(collector.out_features),
                               tuple(options.hidden_sizes)).to(device)
        self.inner_objective = check_loss_module(inner_loss(make_actor(self.net)), self.net)
        self.inner_lr = float(options.inner_lr)
        self.gamma, self.gae_lambda = float(options.gamma), float(options.gae_lambda)
        self.max_kl = float(options.max_kl)
        self.cg_iterations, self.cg_damping = int(options.cg_iterations), float(options.cg_damping)
        self.ls_max_steps = int(options.ls_max_steps)
        self.ls_backtrack_ratio = float(options.ls_backtrack_ratio)
        self.baseline_reg = float(options.baseline_reg)
        self.first_order = bool(options.first_order)
        self.hvp_episodes = options.hvp_episodes

    # -- functional pieces ------------------------------------------------------------------

    def theta(self) -> Params:
        """The meta-parameters θ as a flat name -> tensor dict (the module's own tensors)."""
        return dict(self.net.named_parameters())

    def advantages(self, trajectories: TensorDictBase) -> Tensor:
        """Normalized GAE advantages ``[K, E, T]`` with the per-task refit baseline."""
        return gae_advantages(trajectories, self.gamma, self.gae_lambda, self.baseline_reg)

    def inner_loss(
        self, params: Params, trajectories: TensorDictBase, advantages: Tensor
    ) -> Tensor:
        """Per-task inner loss ``[K]`` under per-task ``params``: by default REINFORCE,
        −mean(log π(a|s)·Â) (the policy-gradient loss of the inner step, MAML paper Sec. 5.3;
        Williams 1992), TorchRL's ``A2CLoss`` batched over tasks."""
        return per_task_objective(self.inner_objective, self.net, as_task_params(params),
                                  trajectories, advantages)

    def inner_step(
        self, theta: Params, trajectories: TensorDictBase, advantages: Tensor, create_graph: bool
    ) -> tuple[Params, Params]:
        """One inner policy-gradient step per task: θ'_k = θ − α ∇L^in_k(θ), ``[K]`` leading (the
        inner step of paper Eq. (7) with the policy-gradient loss, :func:`sgd_step`).

        θ is broadcast to ``[K]``; since L^in_k depends only on slice k, the gradient of Σ_k L^in_k
        with respect to the broadcast tensor holds every task's gradient at once.
        ``create_graph`` keeps the graph for second-order meta-gradients. Returns the broadcast θ
        and the adapted parameters.
        """
        n_tasks = trajectories.batch_size[0]
        expanded = {name: p.expand(n_tasks, *p.shape) for name, p in theta.items()}
        loss = self.inner_loss(expanded, trajectories, advantages).sum()
        grads = torch.autograd.grad(
            loss, list(expanded.values()), create_graph=create_graph and not self.first_order
        )
        adapted = sgd_step(expanded, dict(zip(expanded, grads)), self.inner_lr)
        return expanded, adapted

    def adapt(
        self, theta: Params, trajectories: TensorDictBase, advantages: Tensor, create_graph: bool
    ) -> Params:
        """The adapted per-task parameters θ'_k ``[K]`` of :meth:`inner_step`."""
        return self.inner_step(theta, trajectories, advantages, create_graph)[1]

    def outer_terms(
        self, adapted: Params, valid: TensorDictBase, advantages: Tensor,
        old: tuple[Tensor, Tensor] | None = None,
    ) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor]]:
        """Per-task surrogate loss and KL ``[K]`` of the adapted policies on the post-adaptation
        episodes, against ``old`` (loc, scale) (default: the adapted policies themselves,
        detached). Returns (loss, kl, old)."""
        outputs = loc_scale(self.net, adapted, valid["observation"])
        if old is None:
            old = (outputs[0].detach(), outputs[1].detach())
        loss, kl = self.outer_terms_of_outputs(outputs, valid, advantages, old)
        return loss, kl, old

    @staticmethod
    def outer_terms_of_outputs(
        outputs: Sequence[Tensor], valid: TensorDictBase, advantages: Tensor,
        old: Sequence[Tensor],
    ) -> tuple[Tensor, Tensor]:
        """:meth:`outer_terms` from the adapted policies' (loc, scale) on ``valid``:
        L^out_k = −mean(π_θ'_k(a|s)/π_data(a|s)·Â) and KL_k(π_θ'_k ‖ π_old), each ``[K]``."""
        loc, scale = outputs
        loss = surrogate_loss(
            log_prob(loc, scale, valid["action"]), valid["log_prob"], advantages, valid["mask"]
        )
        return loss, mean_kl(loc, scale, *old, valid["mask"])

    # -- Leader protocol ----------------------------------------------------------------------

    def collect(self, tasks: TensorDictBase, collector: TaskCollector | None = None,
                create_graph: bool = False) -> MetaBatch:
        """Roll out π_θ, adapt every task (one batched inner step), roll out the adapted policies,
        with ``collector`` or the leader's own.

        With ``create_graph`` the adapted parameters keep their graph to θ, for the meta-gradient
        of :meth:`step`; the follower's and the evaluation's data, which are only scored, need
        none.
        """
        collector = self.collector if collector is None else collector
        train = collector.collect(tasks, None, policy=self.net)
        train_advantages = self.advantages(train)
        with torch.enable_grad():
            broadcast, adapted = self.inner_step(
                self.theta(), train, train_advantages, create_graph
            )
        detached = as_task_params({k: v.detach() for k, v in adapted.items()})
        valid = collector.collect(tasks, detached, policy=self.net)
        return MetaBatch(
            train, train_advantages, broadcast, adapted, valid, self.advantages(valid)
        )

    def _hvp_subset(self, batch: MetaBatch) -> slice | None:
        """The episodes of each task the KL's Hessian-vector products use; ``None``: all."""
        if self.hvp_episodes is None or self.hvp_episodes >= batch.train.batch_size[1]:
            return None
        return slice(0, self.hvp_episodes)

    def adapted_outputs(self, adapted: Params, valid: TensorDictBase) -> SurrogateGraph:
        """The adapted parameters θ'_k as detached leaves and the adapted policies' (loc, scale) on
        the episodes ``valid`` computed from them, graph kept."""
        leaves = [a.detach().requires_grad_(True) for a in adapted.values()]
        return SurrogateGraph(
            leaves, loc_scale(self.net, dict(zip(adapted, leaves)), valid["observation"])
        )

    def surrogate_gradient(
        self, batch: MetaBatch, weights: Tensor
    ) -> tuple[Tensor, Tensor, SurrogateGraph]:
        """The weighted post-adaptation surrogate Σ_k w_k L^out_k at the current θ and its flat
        gradient in θ, through the inner step (second order unless ``first_order``).

        Returns (surrogate, gradient, graph): ``graph`` holds the detached adapted parameters as
        leaves and the adapted policies' (loc, scale) on ``batch.valid`` computed from them. Their
        graphs and the inner step's are kept for :meth:`kl_hessian_product` when it uses every
        episode, and freed otherwise.
        """
        keep = self._hvp_subset(batch) is None
        leaves, outputs = self.adapted_outputs(batch.adapted, batch.valid)
        old = (outputs[0].detach(), outputs[1].detach())
        loss_k, _ = self.outer_terms_of_outputs(outputs, batch.valid, batch.valid_advantages, old)
        surrogate = weighted_sum(weights, loss_k)
        # ∇_θ Σ_k w_k L^out_k(θ'_k(θ)) = Σ_k J_k ∇_θ'_k (...), J_k the inner step's Jacobian
        outer_grad = torch.autograd.grad(surrogate, leaves, retain_graph=keep)
        gradient = flatten(torch.autograd.grad(
            list(batch.adapted.values()), list(self.net.parameters()), outer_grad,
            retain_graph=keep,
        ))
        return surrogate.detach(), gradient, SurrogateGraph(leaves, outputs)

    def kl_hessian_product(
        self, batch: MetaBatch, weights: Tensor, graph: SurrogateGraph
    ) -> Callable[[Tensor], Tensor]:
        """v ↦ (∇²_θ Σ_k w_k KL_k(π_θ'_k ‖ π_θ'_k(θ_now)) + damping·I) v, exact and second order
        through the inner step (:func:`~armeta_rl.rl.trpo.meta_kl_hessian_vector_product`).

        On every episode it reuses the surrogate's ``graph``; with ``hvp_episodes = n`` it retakes
        the inner step on the first n training episodes of each task and takes the KL on the first
        n post-adaptation episodes, so both the Jacobian of the inner step and the KL's curvature
        are estimated from that subsample.
        """
        params = list(self.net.parameters())
        broadcast, adapted, valid = batch.broadcast, batch.adapted, batch.valid
        leaves, outputs = graph
        subset = self._hvp_subset(batch)
        if subset is not None:
            valid = batch.valid[:, subset]
            broadcast, adapted = self.inner_step(
                self.theta(), batch.train[:, subset], batch.train_advantages[:, subset], True
            )
            leaves, outputs = self.adapted_outputs(adapted, valid)
        current = tuple(o.detach() for o in outputs)

        def weighted_kl(outs: list[Tensor]) -> Tensor:
            return weighted_sum(weights, mean_kl(*outs, *current, valid["mask"]))

        return meta_kl_hessian_vector_product(
            weighted_kl, outputs, leaves, list(broadcast.values()), list(adapted.values()),
            params, self.cg_damping,
        )

    def trpo_update(self, batch: MetaBatch, weights: Tensor) -> dict[str, float]:
        """One TRPO step on the weighted post-adaptation surrogate Σ_k w_k L^out_k (in place).

        Natural-gradient direction by conjugate gradient on the second-order KL Hessian, scaled to
        the trust region, then backtracking until the surrogate improves with Σ_k w_k KL_k ≤ δ.
        Returns ``trpo_kl`` (Σ_k w_k KL_k of the accepted step), ``trpo_improvement`` (decrease of
        the weighted surrogate) and ``trpo_line_search_steps`` (backtracking steps taken; −1 when
        no step qualified and θ is unchanged).
        """
        w = weights.to(batch.valid["reward"].dtype)
        params = list(self.net.parameters())
        names = list(batch.adapted)
        surrogate, gradient, graph = self.surrogate_gradient(batch, w)
        old = tuple(o.detach() for o in graph.outputs)
        hvp = self.kl_hessian_product(batch, w, graph)
        full_step = trust_region_step(gradient, hvp, self.max_kl, self.cg_iterations)
        del hvp, graph

        def evaluate(vector: Tensor) -> tuple[Tensor, Tensor]:
            vector = vector.detach().requires_grad_(True)
            theta = dict(zip(names, unflatten(vector, params)))
            candidate = self.adapt(theta, batch.train, batch.train_advantages, create_graph=False)
            with torch.no_grad():
                loss_c, kl_c, _ = self.outer_terms(
                    {k: v.detach() for k, v in candidate.items()}, batch.valid,
                    batch.valid_advantages, old,
                )
            return weighted_sum(w, loss_c), weighted_sum(w, kl_c)

        theta0 = flatten(params).detach()
        new_theta, accepted, loss, kl = backtracking_line_search(
            evaluate, theta0, full_step, surrogate, self.max_kl,
            self.ls_max_steps, self.ls_backtrack_ratio,
        )
        with torch.no_grad():
            for p, value in zip(params, unflatten(new_theta, params)):
                p.copy_(value)
        return {
            "trpo_kl": kl.item(),
            "trpo_improvement": surrogate.item() - loss.item(),
            "trpo_line_search_steps": float(-1 if accepted is None else accepted),
        }

    def step(
        self, batch: MetaBatch, weights: TaskWeights
    ) -> tuple[TensorDict, dict[str, float]]:
        """Score the episodes of :meth:`collect` before and after adaptation, then one TRPO step
        on Σ_k w_k L^out_k with ``w = weights(losses)``.

        Returns per-task ``"loss"`` (−return after adaptation), ``"return_pre"``,
        ``"return_post"`` and the adaptation ``"gain"`` (post − pre), and the step's TRPO
        diagnostics (:meth:`trpo_update`). ``batch`` must
        keep its graph to θ (``collect(tasks, create_graph=True)``) for the second-order
        meta-gradient.
        """
        per_task = self.scores(batch)
        return per_task, self.trpo_update(batch, weights(per_task["loss"]))

    def evaluate(self, batch: MetaBatch) -> Tensor:
        """Per-task −(mean return after one inner step) ``[K]``: the adapted policies' returns on
        the post-adaptation episodes of ``batch``.

        The data are θ's own rollouts (``on_policy``), so the follower's losses at θ_{t+1} come
        from a fresh :meth:`collect` after the step (two rollouts and one inner step, no TRPO),
        not from the step's batch collected at θ_t.
        """
        return -episode_returns(batch.valid).mean(-1)

    def scores(self, batch: MetaBatch) -> TensorDict:
        """Per-task ``"loss"`` (:meth:`evaluate`), ``"return_pre"`` and ``"return_post"`` (the
        mean returns before and after adaptation) and the adaptation ``"gain"`` (post − pre)
        of ``batch``, ``[K]``; where the env reports its forward reward, also
        ``"last_step_loss"`` (:func:`last_step_loss`)."""
        losses = self.evaluate(batch)
        return_pre = -self.evaluate_before(batch)
        scores = {"loss": losses, "return_pre": return_pre, "return_post": -losses,
                  "gain": -losses - return_pre}
        if batch.valid.get(FORWARD_REWARD, None) is not None:
            scores["last_step_loss"] = last_step_loss(batch.valid)
        return TensorDict(scores, batch_size=[losses.shape[0]])

    def evaluate_before(self, batch: MetaBatch) -> Tensor:
        """Per-task −(mean return before adaptation) ``[K]``: π_θ's returns on the
        pre-adaptation episodes of ``batch``, the data the inner step adapts on."""
        return -episode_returns(batch.train).mean(-1)

    def adapted_episodes(self, batch: MetaBatch) -> TensorDictBase:
        """The adapted policies' episodes of ``batch`` ``[K, E, T]``, those :meth:`evaluate`
        scores."""
        return batch.valid

    def further_step(self, params: Params, trajectories: TensorDictBase, advantages: Tensor
                     ) -> Params:
        """One more inner step from per-task parameters ``params`` ``[K, ...]`` on their own
        episodes: θ'' = θ' − α ∇L^in(θ'), detached (an evaluation's, no meta-gradient)."""
        leaves = {name: p.detach().requires_grad_(True) for name, p in params.items()}
        with torch.enable_grad():
            loss = self.inner_loss(leaves, trajectories, advantages).sum()
            grads = torch.autograd.grad(loss, list(leaves.values()))
        stepped = sgd_step(leaves, dict(zip(leaves, grads)), self.inner_lr)
        return {name: p.detach() for name, p in stepped.items()}

    def adaptation_curve(self, batch: MetaBatch, steps: int,
                         collector: TaskCollector | None = None) -> Tensor:
        """Per-task loss after 0, 1, ..., ``steps`` inner steps ``[steps + 1, K]``, the meta-test
        curve of pytorch-maml-rl and garage: the first two are :meth:`evaluate_before` and
        :meth:`evaluate` of ``batch``; each further one takes an inner step from the last
        adapted policy on that policy's own episodes and rolls the new one out (with
        ``collector`` or the leader's own)."""
        collector = self.collector if collector is None else collector
        n_tasks = batch.train.batch_size[0]
        tasks = TensorDict({TASK_KEY: batch.train[TASK_KEY][:, 0, 0]}, [n_tasks])
        losses = [self.evaluate_before(batch), self.evaluate(batch)]
        params = {name: p.detach() for name, p in batch.adapted.items()}
        episodes, advantages = batch.valid, batch.valid_advantages
        for _ in range(steps - 1):
            params = self.further_step(params, episodes, advantages)
            episodes = collector.collect(tasks, as_task_params(params), policy=self.net)
            advantages = self.advantages(episodes)
            losses.append(-episode_returns(episodes).mean(-1))
        return torch.stack(losses[: steps + 1])

    def state_dict(self) -> dict[str, Any]:
        return {"policy": self.net.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.net.load_state_dict(state["policy"])


def last_step_loss(trajectories: TensorDictBase) -> Tensor:
    """Per-task −(the forward reward at the last step of each episode), averaged over the
    episodes ``[K]``: the MPTS authors' meta-RL label of a task (``risk.mpts.label=last_step``),
    from episodes ``[K, E, T]`` whose env reports ``"reward_forward"``."""
    last = trajectories["mask"].sum(-1, keepdim=True) - 1  # each episode's last step
    forward = trajectories[FORWARD_REWARD].squeeze(-1).gather(-1, last.clamp(min=0))
    return -forward.squeeze(-1).mean(-1)


def build_maml_trpo(options: MamlTrpoOptions, collector: TaskCollector, device: torch.device,
                    model: Mapping[str, Any]) -> MAMLTRPOLeader:
    """MAML-TRPO with ``options``, its policy sized by the collector's env, on ``device`` (a
    Gaussian MLP policy: no choices in ``model``)."""
    return MAMLTRPOLeader(collector, options=options, device=device)
