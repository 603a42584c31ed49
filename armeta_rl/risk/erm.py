"""Empirical risk minimization: tasks from p0, equal weights (paper Eq. (1); the MAML row of
the paper's table of meta-learning principles)."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torch import Tensor, nn

from armeta_rl.tasks.distributions import TaskDistribution


def uniform_weights(losses: Tensor) -> Tensor:
    """Weights 1/K on the K tasks of a batch: with Σ_k w_k L_k the Monte-Carlo average
    (1/K) Σ_k L(D^Q_{τ_k}, D^S_{τ_k}; θ) of paper Eq. (15), the expected risk of Eq. (1) under
    the distribution the tasks were drawn from."""
    return torch.full_like(losses, 1.0 / losses.numel())


class ERMPrinciple(nn.Module):
    """Plain expected risk under the initial task distribution p0; there is no follower.

    Args:
        initial: p0.

    Examples:
        >>> import torch
        >>> from armeta_rl.risk import ERMPrinciple
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> principle = ERMPrinciple(BoxUniform(TaskSpace(["x"], low=[0.0], high=[1.0])))
        >>> tasks = principle.propose(3)  # from p0
        >>> principle.weights(torch.tensor([1.0, 5.0, 9.0]), tasks)  # the mean, whatever the loss
        tensor([0.3333, 0.3333, 0.3333])
        >>> principle.update_every  # p0 is never updated
        0
    """

    update_every = 0
    needs_next_losses = False
    label = "loss"

    def __init__(self, initial: TaskDistribution) -> None:
        super().__init__()
        self.initial = initial

    def propose(self, n: int) -> TensorDict:
        """``n`` tasks drawn from p0."""
        return self.initial.sample(n)

    def weights(self, losses: Tensor, tasks: TensorDict | None = None) -> Tensor:
        """Uniform weights 1/K, whatever the tasks (:func:`uniform_weights`)."""
        return uniform_weights(losses)

    def update(self, tasks: TensorDict, losses: Tensor) -> dict[str, float]:
        """Nothing to update; the trainer skips it since ``update_every == 0``."""
        return {}
