"""Batched TorchRL environments (batch size ``[tasks, episodes]``) whose task identifiers are
set through the reset TensorDict and kept across automatic resets."""

from armeta_rl.envs.acrobot import AcrobotEnv
from armeta_rl.envs.pendulum import PendulumEnv

__all__ = ["AcrobotEnv", "PendulumEnv"]
