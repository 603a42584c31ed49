"""Meta-learners (leaders): functional MAML and the CNP for regression data, MAML-TRPO for
meta-RL."""

from armeta_rl.learners.base import Leader, TaskWeights
from armeta_rl.learners.cnp import CNPLeader
from armeta_rl.learners.maml import MAMLLeader
from armeta_rl.learners.maml_trpo import MAMLTRPOLeader
from armeta_rl.learners.mlp import make_mlp

__all__ = ["CNPLeader", "Leader", "MAMLLeader", "MAMLTRPOLeader", "TaskWeights", "make_mlp"]
