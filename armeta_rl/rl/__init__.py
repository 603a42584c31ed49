"""Meta-RL building blocks: the Gaussian policy, the linear baseline and GAE advantages, and the
TRPO step (the MAML-TRPO leader that uses them is :mod:`armeta_rl.learners.maml_trpo`)."""

from armeta_rl.rl.policy import GaussianMLP, make_actor

__all__ = ["GaussianMLP", "make_actor"]
