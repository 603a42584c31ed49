"""Task identifiers: the box they live in, the initial distributions p0 over it, the key they
travel under, and the transform that draws them at every reset of a TorchRL env."""

from armeta_rl.tasks.distributions import (
    BoxUniform,
    TaskDistribution,
    TruncatedNormal,
    make_initial,
)
from armeta_rl.tasks.protocol import TASK_KEY
from armeta_rl.tasks.space import TaskSpace
from armeta_rl.tasks.transform import TaskTransform, finished_episodes

__all__ = [
    "TASK_KEY",
    "BoxUniform",
    "TaskDistribution",
    "TaskSpace",
    "TaskTransform",
    "TruncatedNormal",
    "finished_episodes",
    "make_initial",
]
