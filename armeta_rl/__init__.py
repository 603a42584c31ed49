"""armeta_rl: robust meta-learning and meta-RL with an explicit, adversarial task distribution.

Implements "Robust Fast Adaptation from Adversarially Explicit Task Distribution Generation"
(KDD'25): a normalizing-flow distribution adversary p_φ over task identifiers plays a Stackelberg
game against a meta-learner (MAML, CNP, MAML-TRPO).

``armeta_rl.load_run(path)`` loads a run directory (:func:`armeta_rl.runs.load_run`); it is
imported when first used, so ``import armeta_rl`` (and the command lines' ``--help``) stays
light.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    if name in ("load_run", "Run"):
        from armeta_rl import runs

        return getattr(runs, name)
    raise AttributeError(f"module 'armeta_rl' has no attribute {name!r}")
