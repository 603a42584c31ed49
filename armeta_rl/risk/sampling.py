"""Any risk principle as a task sampler for a training loop that is not ours.

:class:`PrincipleSampler` gives a principle (ERM, DR, TR, DRO, AR, MPTS, PDTS) the verbs of
:class:`~armeta_rl.adversary.TaskSampler` and of p0 itself: ``sample(n)`` tasks, run them in any
loop (TorchRL PPO, say), hand back one loss per task with ``update(tasks, losses)``. A loop that
weighs its per-task losses asks :meth:`PrincipleSampler.weights` (uniform for ERM, AR, MPTS and
PDTS; the tail for DR; the group weights for TR and DRO).

The losses a loop hands back are the ones it has: for a follower of the game
(``needs_next_losses``, AR, TR, DRO) our trainer evaluates the learner again after its step, an
outside loop usually passes the batch's own losses (the flow adversary's :class:`TaskSampler`
does the same).
"""

from __future__ import annotations

from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.risk.predictive import check_batch_size, checked_losses, task_params


class PrincipleSampler:
    """Tasks from a risk principle, and its update on their losses.

    Args:
        principle: any :class:`~armeta_rl.risk.base.RiskPrinciple` (e.g.
            ``MPTSPrinciple(BoxUniform(space))``); it is updated every ``update_every`` calls of
            :meth:`update`, as in the trainer.

    Examples:
        >>> import torch
        >>> from armeta_rl.risk import PrincipleSampler, TailRiskPrinciple
        >>> from armeta_rl.risk.tail import DrOptions
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> _ = torch.manual_seed(0)
        >>> p0 = BoxUniform(TaskSpace(["x"], low=[0.0], high=[1.0]))
        >>> sampler = PrincipleSampler(TailRiskPrinciple(p0, DrOptions(alpha=0.5)))
        >>> tasks = sampler.sample(4)  # from p0
        >>> tasks["params"].flatten()
        tensor([0.9701, 0.7078, 0.4594, 0.9207])
        >>> losses = torch.tensor([3.0, 1.0, 4.0, 2.0])  # the outside loop's losses on them
        >>> sampler.weights(losses, tasks)  # CVaR_0.5: the worst half, tasks 0 and 2
        tensor([0.5000, 0.0000, 0.5000, 0.0000])
        >>> sampler.update(tasks, losses)  # VaR_0.5 = 3, CVaR_0.5 = (3 + 4) / 2
        {'risk/var': 3.0, 'risk/cvar': 3.5}
    """

    def __init__(self, principle: RiskPrinciple) -> None:
        self.principle = principle
        self.calls = 0

    def sample(self, n: int) -> TensorDict:
        """Tasks ``{"params": [K, d], "log_prob": [K]}`` for a batch of ``n`` (K = n, or more for a
        principle that oversamples, such as DR with ``oversample``)."""
        return self.principle.propose(check_batch_size("n", n))

    def weights(self, losses: Tensor, tasks: TensorDict) -> Tensor:
        """The principle's weights ``[K]`` of the tasks' losses (they sum to one)."""
        return self.principle.weights(losses, tasks)

    def update(self, tasks: TensorDictBase | Tensor, losses: Tensor) -> dict[str, float]:
        """Update the principle on the losses ``[K]`` of ``tasks`` (a task TensorDict or its
        identifiers ``[K, d]``); returns its scalars (none between updates).

        Raises:
            ValueError: losses that are not one per task.
            TrainingDiverged: non-finite losses.
        """
        params = task_params(tasks)
        losses = checked_losses(losses, len(params), "task sampler update")
        self.calls += 1
        every = self.principle.update_every
        if not every or self.calls % every:
            return {}
        if not isinstance(tasks, TensorDictBase):
            tasks = TensorDict({"params": params}, batch_size=[len(params)])
        return self.principle.update(tasks, losses.to(params.device))
