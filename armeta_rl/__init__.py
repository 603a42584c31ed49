"""armeta_rl: robust meta-learning and meta-RL with an explicit, adversarial task distribution.

Implements "Robust Fast Adaptation from Adversarially Explicit Task Distribution Generation"
(KDD'25): a normalizing-flow distribution adversary p_φ over task identifiers plays a Stackelberg
game against a meta-learner (MAML, CNP, MAML-TRPO).
"""

__version__ = "0.1.0"
