"""Meta-learners (leaders): functional MAML, ANIL and the CNP for regression data, MAML-TRPO
and MAML-PPO for meta-RL."""

from armeta_rl.learners.anil import ANILLeader
from armeta_rl.learners.base import Leader, TaskWeights
from armeta_rl.learners.cnp import CNPLeader
from armeta_rl.learners.maml import MAMLLeader
from armeta_rl.learners.maml_ppo import MAMLPPOLeader
from armeta_rl.learners.maml_trpo import MAMLTRPOLeader
from armeta_rl.learners.mlp import make_mlp

__all__ = ["ANILLeader", "CNPLeader", "Leader", "MAMLLeader", "MAMLPPOLeader", "MAMLTRPOLeader",
           "TaskWeights", "make_mlp"]
