"""Meta-learners (leaders) for regression data: functional MAML and the CNP."""

from armeta_rl.learners.base import Leader, TaskWeights
from armeta_rl.learners.cnp import CNPLeader
from armeta_rl.learners.maml import MAMLLeader
from armeta_rl.learners.mlp import make_mlp

__all__ = ["CNPLeader", "Leader", "MAMLLeader", "TaskWeights", "make_mlp"]
