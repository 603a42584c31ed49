"""Task identifiers: the box they live in and the initial distributions p0 over it."""

from armeta_rl.tasks.distributions import (
    BoxUniform,
    TaskDistribution,
    TruncatedNormal,
    make_initial,
)
from armeta_rl.tasks.protocol import TASK_KEY
from armeta_rl.tasks.space import TaskSpace

__all__ = [
    "TASK_KEY",
    "BoxUniform",
    "TaskDistribution",
    "TaskSpace",
    "TruncatedNormal",
    "make_initial",
]
