"""``risk.ar``'s keys (:class:`ArOptions`): the flow adversary's and its follower's settings,
their types, ranges and defaults, in one place for both of their users,
:class:`~armeta_rl.risk.adversarial.AdversarialPrinciple` (a training run's AR principle) and
:class:`~armeta_rl.adversary.TaskSampler` (the adversary in another training loop)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.adversary.flows import DEFAULT_FLOW, FLOW_KINDS
from armeta_rl.adversary.objective import BASELINES, SIGNALS, STEPS, Follower
from armeta_rl.fields import Section, above, at_least, inside, key, one_of, register


@register("risk.ar")
@dataclass(frozen=True)
class ArOptions(Section):
    """``risk.ar``: the keys of :class:`AdversarialPrinciple` and of its flow adversary, their
    types, ranges and defaults.

    Attributes:
        flow: the flow of p_φ the builder makes, ``"spline"`` (rational-quadratic spline
            coupling flow) or ``"planar"`` (the paper's leaky-ReLU planar flow); a principle built
            from Python is handed its :class:`FlowAdversary` and ignores it and ``flow_kwargs``.
        flow_kwargs: the flow's own arguments (spline: ``layers``, ``bins``, ``hidden``,
            ``blocks``; planar: ``layers``, ``activation``, ``eps``), checked by the flow.
        lam: Lagrange multiplier λ ≥ 0 of E_{p0}[ln p_φ(τ)].
        update_every: follower update interval u in leader steps.
        step: how the follower steps: ``"adam"`` (the paper's: Adam at rate ``lr``,
            cosine-annealed over the run) or ``"natural"`` (natural-gradient steps that each
            move p_φ by KL ``max_kl``, whatever the run's length and the flow's parametrization;
            :func:`~armeta_rl.adversary.objective.natural_ascent_step`).
        lr: Adam learning rate of the follower, cosine-annealed over the run.
        max_kl: the natural step's KL δ between p_φ before and after each update.
        grad_clip: maximum norm of φ's gradient for Adam, or ``None`` for no clipping.
        baseline: score-function baseline, ``"mean"`` or ``"leave_one_out"``.
        initial_samples: M, the number of fresh p0 samples for the λ term of the gradient.
        signal: what the adversary ascends: ``"loss"`` (the paper's task loss L) or
            ``"regret"``, L − L* against the benchmark's reference loss L* (minus the best
            return any policy gets on the task, where the benchmark knows it: the point robot's
            straight path), so a task counts as hard for what the learner misses there, not
            for how low its returns are in themselves.
        standardize: divide the signal's advantages by their batch standard deviation: the
            loss term of J has unit scale, so λ is relative to the loss scale and one value
            serves MSE and returns (docs/meta-rl.md).
        compile: ``torch.compile`` the flow's passes (the draw of
            :meth:`AdversarialPrinciple.propose` and the log-densities of
            :meth:`AdversarialPrinciple.update`): ``False``, ``True`` (inductor) or a backend
            name; see :mod:`armeta_rl.compiling`.
    """

    # spline (exact, box-preserving) or planar (the paper's 2 layers)
    flow: str = one_of(*FLOW_KINDS, default=DEFAULT_FLOW)
    # spline: layers (default 1 on a 2-D box, else 2), bins, hidden, blocks; checked by the flow
    flow_kwargs: dict[str, Any] = key(default={})
    # the paper's: 0.2 regression/sys-id, 0 for RL (the RL benchmarks set it)
    lam: float = key("must be >= 0 (λ ≥ 0)", lambda v: v >= 0, default=0.2)
    update_every: int = at_least(1, default=1)
    step: str = one_of(*STEPS, default="adam")  # adam (the paper's) or natural
    # the follower's step size, cosine-annealed over the run (docs/notes/history.md: the
    # authors' code's schedule and this default)
    lr: float = inside(0, 1, "(]", default=0.001)
    max_kl: float = inside(0, 1, "(]", default=0.005)  # the natural step's KL per update
    # clips φ's gradient norm (null: off); it acts in nearly every update
    # (docs/notes/history.md)
    grad_clip: float | None = above(0, default=1.0)
    baseline: str = one_of(*BASELINES, default="mean")  # mean (the paper's) or leave_one_out
    initial_samples: int = at_least(1, default=256)
    signal: str = one_of(*SIGNALS, default="loss")  # loss (the paper's) or regret
    standardize: bool = key(default=False)  # λ relative to the loss scale
    compile: Any = key(default=False)  # checked by armeta_rl.compiling


def follower_of(adversary: FlowAdversary, options: ArOptions, total_updates: int | None,
                log_prob: Callable[[Tensor], Tensor] | None = None) -> Follower:
    """The :class:`~armeta_rl.adversary.objective.Follower` of ``adversary`` with ``options``'
    settings: Adam ascending J in φ at rate ``options.lr``, cosine-annealed to 0 over
    ``total_updates`` updates (``None``: a constant rate), or with ``options.step ==
    "natural"`` natural steps of KL ``options.max_kl`` (no optimizer, no schedule);
    ``log_prob`` as the follower's."""
    settings = {"lam": float(options.lam), "baseline": options.baseline,
                "initial_samples": options.initial_samples, "grad_clip": options.grad_clip,
                "log_prob": log_prob, "standardize": options.standardize}
    if options.step == "natural":
        return Follower(adversary, None, max_kl=float(options.max_kl), **settings)
    optimizer = torch.optim.Adam(adversary.parameters(), lr=options.lr, maximize=True,
                                 fused=True)
    scheduler = (None if total_updates is None
                 else torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=total_updates))
    return Follower(adversary, optimizer, scheduler, **settings)
