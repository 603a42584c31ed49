"""The game loop, evaluation, checkpoints and whole training runs."""

from armeta_rl.trainers.checkpoint import RunCheckpoint
from armeta_rl.trainers.evaluation import cvar, evaluate_on, summarize
from armeta_rl.trainers.game import GameTrainer

__all__ = ["GameTrainer", "RunCheckpoint", "cvar", "evaluate_on", "summarize"]
