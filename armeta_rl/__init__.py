"""armeta_rl: robust meta-learning and meta-RL with an explicit, adversarial task distribution.

Implements "Robust Fast Adaptation from Adversarially Explicit Task Distribution Generation"
(KDD'25): a normalizing-flow distribution adversary p_φ over task identifiers plays a Stackelberg
game against a meta-learner (MAML, CNP, MAML-TRPO).
"""

# registers what configs/ use: ${method_name:...} and the learners' options (learner_options)
import armeta_rl.config  # noqa: F401

__version__ = "0.1.0"
