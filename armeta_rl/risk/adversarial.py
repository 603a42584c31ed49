"""The AR risk principle: the flow adversary p_φ as the follower of the Stackelberg game.

Tasks come from p_φ and weigh equally in the leader's objective (paper Eq. (15)). After
the leader's step the follower takes one stochastic gradient *ascent* step on
J(θ_{t+1}, φ) = E_{p_φ}[L] + λ·E_{p0}[ln p_φ] (paper Eq. (6) and the alternating GDA of Eq.
(14)) with the score-function estimate of Eq. (17), Adam and a
cosine learning-rate schedule (paper appendix "Distribution Adversary Implementations"), or
natural-gradient steps of a fixed KL (``risk.ar.step=natural``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor, nn

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.adversary.objective import follower_step, regret
from armeta_rl.adversary.options import ArOptions, follower_of
from armeta_rl.compiling import compile_backend, maybe_compile
from armeta_rl.errors import ConfigError
from armeta_rl.risk.erm import uniform_weights
from armeta_rl.tasks.distributions import TaskDistribution
from armeta_rl.tasks.protocol import TASK_KEY


class AdversarialPrinciple(nn.Module):
    """AR-MAML / AR-CNP's task source: the flow adversary, updated every ``update_every`` steps.

    ``state_dict()`` holds the adversary's parameters plus, as torch's ``_extra_state``, the Adam
    and scheduler states, none for natural steps (plain tensors, numbers and lists:
    ``torch.load(weights_only=True)`` reads it). Like any ``nn.Module`` state dict its tensors
    alias the live ones; copy before mutating.

    Args:
        adversary: p_φ (its ``base`` is p0).
        options: the keys of ``risk.ar`` (:class:`ArOptions`): λ, the follower's step, its
            baseline and schedule.
        total_updates: ``T_max`` of Adam's cosine schedule (≥ 1); the rate reaches 0 after that
            many follower updates (the builder: ``trainer.iterations // update_every``).
        reference_loss: the benchmark's reference loss L*(τ) ``[K]`` of identifiers ``[K, d]``,
            needed by ``signal="regret"`` (the builder: the collector's ``reference_loss``).

    Examples:
        >>> import torch
        >>> from armeta_rl.adversary import FlowAdversary
        >>> from armeta_rl.risk import AdversarialPrinciple
        >>> from armeta_rl.risk.adversarial import ArOptions
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> _ = torch.manual_seed(0)
        >>> space = TaskSpace(["x"], low=[0.0], high=[1.0])
        >>> adversary = FlowAdversary(space, BoxUniform(space))  # p_φ = p0 = U[0, 1] at first
        >>> options = ArOptions(lam=0.0, step="natural", max_kl=0.01)
        >>> principle = AdversarialPrinciple(adversary, options, total_updates=10)
        >>> tasks = principle.propose(64)
        >>> stats = principle.update(tasks, losses=tasks["params"][:, 0])  # the loss is x
        >>> round(stats["adversary/objective"], 2)  # J = E_p0[x] ≈ 1/2, before the step
        0.51
        >>> probe = torch.tensor([[0.1], [0.5], [0.9]])
        >>> adversary.log_prob(probe).exp().detach()  # p_φ after one step: mass moved to x = 1
        tensor([0.8508, 0.9722, 1.0923], dtype=torch.float64)
    """

    needs_next_losses = True
    label = "loss"

    def __init__(
        self,
        adversary: FlowAdversary,
        options: ArOptions = ArOptions(),
        total_updates: int = 1000,
        reference_loss: Callable[[Tensor], Tensor] | None = None,
    ) -> None:
        super().__init__()
        if isinstance(total_updates, bool) or not isinstance(total_updates, int) or (
            total_updates < 1
        ):
            raise ConfigError("risk.ar.total_updates", total_updates, "must be an integer >= 1")
        self.adversary = adversary
        if options.signal == "regret" and reference_loss is None:
            raise ConfigError("risk.ar.signal", options.signal,
                              "needs a benchmark that knows a reference return (the point "
                              "robot's); allowed here: loss")
        self.signal, self.reference_loss = options.signal, reference_loss
        self.update_every = options.update_every
        backend = compile_backend("risk.ar.compile", options.compile)
        self._push_forward = maybe_compile(adversary.push_forward, backend)
        self.follower = follower_of(adversary, options, total_updates,
                                    log_prob=maybe_compile(adversary.log_prob, backend))

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
        """One follower ascent step on the losses of ``tasks`` at θ_{t+1}
        (:func:`~armeta_rl.adversary.objective.follower_step`: paper Eq. (14), second line;
        gradient of Eq. (17)); a diverged step raises ``TrainingDiverged`` and the run stops at
        its last checkpoint.

        Logs ``adversary/objective`` (the estimate of J), ``adversary/entropy`` (from the K task
        samples) and ``adversary/kl_p0`` (from the ``initial_samples`` p0 samples), all of p_φ
        before the step and free by-products of the surrogate; ``adversary/grad_norm`` (before
        clipping) and ``adversary/lr`` (Adam's rate used) or ``adversary/step_kl`` (the natural
        step's KL). Precise entropy and KL of the final p_φ go
        to the evaluation report. With ``signal="regret"`` the follower ascends L − L* against
        the benchmark's reference loss (:func:`~armeta_rl.adversary.objective.regret`)."""
        if self.signal == "regret":
            losses = losses.detach().to(torch.float64)
            losses = regret(losses, self.reference_loss(tasks[TASK_KEY]).to(losses))
        stats = follower_step(self.follower, tasks, losses)
        return {f"adversary/{name}": stats[name]
                for name in ("objective", "entropy", "kl_p0", "lr", "step_kl", "grad_norm")
                if name in stats}

    @property
    def optimizer(self) -> torch.optim.Optimizer | None:
        """The follower's Adam (ascent); ``None`` for natural steps."""
        return self.follower.optimizer

    @property
    def scheduler(self) -> torch.optim.lr_scheduler.CosineAnnealingLR | None:
        """The follower's cosine learning-rate schedule; ``None`` for natural steps."""
        return self.follower.scheduler

    def get_extra_state(self) -> dict[str, Any]:
        """Optimizer and learning-rate schedule, stored in ``state_dict()["_extra_state"]``
        (empty for natural steps, which keep no state besides φ)."""
        if self.optimizer is None:
            return {}
        return {"optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict()}

    def set_extra_state(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`get_extra_state` returned. A schedule saved with another horizon
        (a run resumed with more ``trainer.iterations``) is re-planned for this one's
        (:meth:`replan`)."""
        if self.optimizer is None:
            return
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
