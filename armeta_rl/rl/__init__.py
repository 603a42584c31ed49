"""Meta-RL: Gaussian policy, linear baseline, GAE inner step and the MAML-TRPO leader
(``armeta_rl.rl.maml_trpo.MAMLTRPOLeader``)."""

from armeta_rl.rl.policy import GaussianMLP, make_actor

__all__ = ["GaussianMLP", "make_actor"]
