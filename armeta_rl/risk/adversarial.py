"""The AR risk principle: the flow adversary p_φ as the follower of the Stackelberg game.

Tasks come from p_φ and weigh equally in the leader's objective (paper Eq. (15)). After
the leader's step the follower takes one stochastic gradient *ascent* step on
J(θ_{t+1}, φ) = E_{p_φ}[L] + λ·E_{p0}[ln p_φ] (paper Eq. (6) and the alternating GDA of Eq.
(14)) with the score-function estimate of Eq. (17), Adam and a
cosine learning-rate schedule (paper appendix "Distribution Adversary Implementations").
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor, nn

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.adversary.flows import DEFAULT_FLOW, FLOW_KINDS
from armeta_rl.adversary.objective import BASELINES, adversary_surrogate, surrogate_gradient
from armeta_rl.compiling import compile_backend, maybe_compile
from armeta_rl.errors import ConfigError, TrainingDiverged
from armeta_rl.fields import Section, above, at_least, key, one_of, register
from armeta_rl.risk.erm import uniform_weights
from armeta_rl.tasks.distributions import TaskDistribution
from armeta_rl.tasks.protocol import TASK_KEY


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
        lr: Adam learning rate of the follower, cosine-annealed over the run.
        grad_clip: maximum norm of φ's gradient, or ``None`` for no clipping.
        baseline: score-function baseline, ``"mean"`` or ``"leave_one_out"``.
        initial_samples: M, the number of fresh p0 samples for the λ term of the gradient.
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
    # The code's: 1e-4 every 10th iteration; the paper profile's choice: docs/protocol.md,
    # section 2.
    lr: float = above(0, default=0.001)
    # Active in nearly every update, not only early (docs/protocol.md, section 5); the code clips
    # at 5; None (null): off.
    grad_clip: float | None = above(0, default=1.0)
    baseline: str = one_of(*BASELINES, default="mean")  # mean (the paper's) or leave_one_out
    initial_samples: int = at_least(1, default=256)
    compile: Any = key(default=False)  # checked by armeta_rl.compiling


class AdversarialPrinciple(nn.Module):
    """AR-MAML / AR-CNP's task source: the flow adversary, updated every ``update_every`` steps.

    ``state_dict()`` holds the adversary's parameters plus, as torch's ``_extra_state``, the Adam
    and scheduler states (plain tensors, numbers and lists: ``torch.load(weights_only=True)``
    reads it). Like any ``nn.Module`` state dict its tensors alias the live ones; copy before
    mutating.

    Args:
        adversary: p_φ (its ``base`` is p0).
        options: the keys of ``risk.ar`` (:class:`ArOptions`): λ, the follower's step, its
            baseline and schedule.
        total_updates: ``T_max`` of the cosine schedule (≥ 1); the rate reaches 0 after that many
            follower updates (the builder: ``trainer.iterations // update_every``).
    """

    needs_next_losses = True

    def __init__(
        self,
        adversary: FlowAdversary,
        options: ArOptions = ArOptions(),
        total_updates: int = 1000,
    ) -> None:
        super().__init__()
        if isinstance(total_updates, bool) or not isinstance(total_updates, int) or (
            total_updates < 1
        ):
            raise ConfigError("risk.ar.total_updates", total_updates, "must be an integer >= 1")
        self.adversary = adversary
        self.lam, self.update_every = float(options.lam), options.update_every
        self.grad_clip = options.grad_clip
        self.baseline, self.initial_samples = options.baseline, options.initial_samples
        self._phi = list(adversary.parameters())
        backend = compile_backend("risk.ar.compile", options.compile)
        self._log_prob = maybe_compile(adversary.log_prob, backend)
        self._push_forward = maybe_compile(adversary.push_forward, backend)
        self.optimizer = torch.optim.Adam(self._phi, lr=options.lr, maximize=True, fused=True)
        self.scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(
            self.optimizer, T_max=total_updates
        )
        self._backup: list[Tensor] = []

    @property
    def initial(self) -> TaskDistribution:
        """p0, the adversary's base distribution."""
        return self.adversary.base

    @torch.no_grad()
    def propose(self, n: int) -> TensorDict:
        """``n`` tasks τ = g_φ(τ0), τ0 ~ p0, drawn from p_φ (paper Eq. (9)) with their
        log-probabilities (Eq. (10))."""
        return self.adversary.as_tasks(*self._push_forward(self.initial.sample_params(n)))

    def weights(self, losses: Tensor, tasks: TensorDict | None = None) -> Tensor:
        """Uniform weights 1/K: the leader minimizes the plain average over tasks from p_φ (paper
        Eq. (15), :func:`~armeta_rl.risk.erm.uniform_weights`)."""
        return uniform_weights(losses)

    def update(self, tasks: TensorDict, losses: Tensor) -> dict[str, float]:
        """One follower ascent step on the losses of ``tasks`` at θ_{t+1} (paper Eq.
        (14), second line; gradient of Eq. (17)).

        Logs ``adversary/objective`` (the estimate of J), ``adversary/entropy`` (from the K task
        samples) and ``adversary/kl_p0`` (from the ``initial_samples`` p0 samples), all of p_φ
        before the step and free by-products of the surrogate; ``adversary/lr`` (the rate used)
        and ``adversary/grad_norm`` (before clipping). Precise entropy and KL of the final p_φ go
        to the evaluation report. After the step the new p_φ's log-density at ``tasks`` checks the
        new flow; it draws no random numbers.

        Raises:
            TrainingDiverged: if the losses, the surrogate, its gradient, the new parameters or the
                new density are not finite; the parameters and optimizer are left as they were.
        """
        losses = losses.detach().to(torch.float64)
        if not torch.isfinite(losses).all():
            raise TrainingDiverged(f"adversary update got non-finite losses: {losses.tolist()}")
        initial = self.initial.sample_params(self.initial_samples)
        surrogate, stats = adversary_surrogate(
            self.adversary, tasks, losses, self.lam, initial, self.baseline, self._log_prob
        )
        if not torch.isfinite(surrogate):
            raise TrainingDiverged(
                "adversary surrogate is not finite (a task outside the box, "
                "or a non-finite flow log-density)"
            )
        grad_norm = surrogate_gradient(surrogate, self.optimizer, self._phi, self.grad_clip)
        if not torch.isfinite(grad_norm):
            self.optimizer.zero_grad(set_to_none=True)
            raise TrainingDiverged(f"adversary gradient is not finite (norm {float(grad_norm)})")
        lr = self.optimizer.param_groups[0]["lr"]
        self._ascend(tasks)
        return {
            "adversary/objective": stats["objective"],
            "adversary/entropy": stats["entropy"],
            "adversary/kl_p0": stats["kl_p0"],
            "adversary/lr": float(lr),
            "adversary/grad_norm": float(grad_norm),
        }

    def _ascend(self, tasks: TensorDict) -> None:
        """φ ← Adam-ascent step on the gradients already set (paper Eq. (14), second line), then
        one step of the schedule; undone, with ``TrainingDiverged``, if the new parameters or the
        new log-density at ``tasks`` are not finite."""
        snapshot = self._snapshot()
        self.optimizer.step()
        self.scheduler.step()
        self.optimizer.zero_grad(set_to_none=True)
        largest = torch.nn.utils.get_total_norm(self._phi, norm_type=math.inf, foreach=True)
        with torch.no_grad():
            log_prob = self._log_prob(tasks[TASK_KEY])
        if not (torch.isfinite(largest) and torch.isfinite(log_prob).all()):
            self._restore(snapshot)
            raise TrainingDiverged("adversary step produced non-finite parameters or log-densities")

    def get_extra_state(self) -> dict[str, Any]:
        """Optimizer and learning-rate schedule, stored in ``state_dict()["_extra_state"]``."""
        return {"optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict()}

    def set_extra_state(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`get_extra_state` returned. A schedule saved with another horizon
        (a run resumed with more ``trainer.iterations``) is re-planned for this one's
        (:meth:`replan`)."""
        total_updates = self.scheduler.T_max
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        if self.scheduler.T_max != total_updates:
            self.replan(total_updates)

    def replan(self, total_updates: int) -> None:
        """Re-plan the cosine schedule for ``total_updates`` follower updates in all, keeping the
        updates done: from the next update on, the learning rate is bit for bit the one a run
        planned for ``total_updates`` from the start uses there (its recursion is replayed on a
        probe optimizer), and it reaches 0 after ``total_updates`` updates."""
        probe = torch.optim.SGD(
            [{"params": [torch.zeros(1, requires_grad=True)], "lr": lr}
             for lr in self.scheduler.base_lrs]
        )
        planned = torch.optim.lr_scheduler.CosineAnnealingLR(probe, T_max=total_updates)
        for _ in range(self.scheduler.last_epoch):
            probe.step()
            planned.step()
        self.scheduler.load_state_dict(planned.state_dict())
        for group, lr in zip(self.optimizer.param_groups, planned.get_last_lr(), strict=True):
            group["lr"] = lr

    @torch.no_grad()
    def _snapshot(self) -> tuple[list[Tensor], bool, dict[str, Any]]:
        """A copy of the parameters and Adam's moments and step counts, whether Adam has state
        yet, and the schedule: what :meth:`_restore` needs to undo a step. The copy goes into
        buffers kept between updates, in one foreach copy, rather than concatenating the ~100
        small tensors afresh."""
        tensors = self._state_tensors()
        if [b.shape for b in self._backup] != [t.shape for t in tensors]:
            self._backup = [torch.empty_like(t) for t in tensors]
        torch._foreach_copy_(self._backup, tensors)
        return self._backup, bool(self.optimizer.state), copy.deepcopy(self.scheduler.state_dict())

    def _state_tensors(self) -> list[Tensor]:
        states = [self.optimizer.state[p] for p in self._phi if p in self.optimizer.state]
        return self._phi + [s[k] for s in states for k in sorted(s)]

    @torch.no_grad()
    def _restore(self, snapshot: tuple[list[Tensor], bool, dict[str, Any]]) -> None:
        backup, had_state, schedule = snapshot
        tensors = self._state_tensors() if had_state else self._phi
        torch._foreach_copy_(tensors, backup[: len(tensors)])
        if not had_state:
            self.optimizer.state.clear()
        self.scheduler.load_state_dict(schedule)
        last_lrs = self.scheduler.get_last_lr()
        for group, lr in zip(self.optimizer.param_groups, last_lrs, strict=True):
            group["lr"] = lr
