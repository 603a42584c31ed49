"""The flow adversary for any training loop: draw tasks, then ascend on their losses.

:class:`TaskSampler` is the follower of the paper's game without the rest of our trainer: a loop
(TorchRL PPO, say) asks it for ``n`` tasks, runs them, and hands back one loss per task; the
sampler takes one ascent step of J(φ) = E_{p_φ}[L] + λ·E_{p0}[ln p_φ] (paper Eq. (6)) with
the score-function surrogate of Eq. (17), Adam and, optionally, the cosine learning-rate
schedule: the follower step of :class:`~armeta_rl.risk.adversarial.AdversarialPrinciple`
(:func:`~armeta_rl.adversary.objective.follower_step`). It keeps no
state between calls beyond φ, Adam's moments and the schedule: the tasks a loss belongs to are
passed back with it.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.adversary.objective import follower_step
from armeta_rl.adversary.options import ArOptions, follower_of
from armeta_rl.errors import ConfigError
from armeta_rl.tasks import TASK_KEY


class TaskSampler:
    """Tasks from the flow adversary p_φ, and its follower update on their losses.

    Args:
        adversary: p_φ (its ``base`` is p0), e.g. ``FlowAdversary(space, BoxUniform(space))``.
        lam: Lagrange multiplier λ ≥ 0 of the KL(p0 ‖ p_φ) constraint (the paper uses 0 for
            continuous control).
        lr: Adam learning rate, in (0, 1].
        total_updates: ``T_max`` of a cosine schedule that takes Adam's rate to 0 after that
            many updates, or ``None`` for a constant rate.
        step: ``"adam"`` or ``"natural"`` (each update moves p_φ by KL ``max_kl``,
            :func:`~armeta_rl.adversary.objective.natural_ascent_step`).
        max_kl: the natural step's KL per update, in (0, 1].
        grad_clip: maximum gradient norm, or ``None`` for no clipping.
        baseline: score-function baseline, ``"mean"`` or ``"leave_one_out"``.
        initial_samples: M, the fresh p0 samples of the λ term's gradient (≥ 1).

    ``lam``, ``lr``, ``grad_clip``, ``baseline``, ``initial_samples``, ``step`` and ``max_kl``
    are ``risk.ar``'s keys,
    checked by :class:`~armeta_rl.adversary.options.ArOptions` (a refusal names the argument).

    Examples:
        >>> from armeta_rl.adversary import FlowAdversary, TaskSampler
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> space = TaskSpace(["x"], low=[0.0], high=[1.0])
        >>> sampler = TaskSampler(FlowAdversary(space, BoxUniform(space)), lam=0.0, lr=1e-2)
        >>> tasks = sampler.sample(16)
        >>> stats = sampler.update(tasks, losses=tasks["params"][:, 0])  # one ascent step of φ
        >>> sorted(stats)
        ['entropy', 'grad_norm', 'kl_p0', 'loss_mean', 'lr', 'objective']
        >>> natural = TaskSampler(FlowAdversary(space, BoxUniform(space)), step="natural",
        ...                       max_kl=0.01)
        >>> tasks = natural.sample(16)
        >>> round(natural.update(tasks, losses=tasks["params"][:, 0])["step_kl"], 2)  # ≈ δ
        0.01
    """

    def __init__(
        self,
        adversary: FlowAdversary,
        lam: float = 0.0,
        lr: float = 1e-3,
        total_updates: int | None = None,
        grad_clip: float | None = 1.0,
        baseline: str = "mean",
        initial_samples: int = 256,
        step: str = "adam",
        max_kl: float = 0.005,
    ) -> None:
        try:
            options = ArOptions(lam=lam, lr=lr, grad_clip=grad_clip, baseline=baseline,
                                initial_samples=initial_samples, step=step, max_kl=max_kl)
        except ConfigError as error:
            raise ConfigError(error.key.removeprefix(f"{ArOptions.section}."), error.value,
                              error.allowed) from None
        if total_updates is not None and not (isinstance(total_updates, int)
                                               and total_updates >= 1):
            raise ConfigError("total_updates", total_updates, "an integer >= 1 or null")
        self.adversary = adversary
        self.follower = follower_of(adversary, options, total_updates)

    def sample(self, n: int) -> TensorDict:
        """``n`` tasks ``{"params": [n, d], "log_prob": [n]}`` drawn from p_φ."""
        if isinstance(n, bool) or not (isinstance(n, int) and n >= 1):
            raise ConfigError("n", n, "must be an integer >= 1")
        return self.adversary.sample(n)

    def update(
        self, tasks: TensorDictBase | torch.Tensor, losses: torch.Tensor
    ) -> dict[str, float]:
        """One ascent step of φ on the losses ``[K]`` of ``tasks`` (``{"params": [K, d]}`` or the
        params themselves; they need not come from :meth:`sample`, but the estimate is unbiased
        only for samples of the current p_φ). Returns the surrogate's statistics at the φ before
        the step (``objective``, ``loss_mean``, ``entropy``, ``kl_p0``), ``grad_norm`` (before
        clipping) and ``lr`` (Adam) or ``step_kl`` (natural steps).

        Raises:
            ValueError: losses that are not one per task.
            TrainingDiverged: non-finite losses, gradient or new φ
                (:func:`~armeta_rl.adversary.objective.follower_step`).
        """
        params = tasks[TASK_KEY] if isinstance(tasks, TensorDictBase) else tasks
        losses = torch.as_tensor(losses).detach().to(params.device, torch.float64)
        if losses.shape != (len(params),):
            raise ValueError(f"'losses' has shape {tuple(losses.shape)}: one loss per task, "
                             f"shape ({len(params)},)")
        return follower_step(self.follower, params, losses)
