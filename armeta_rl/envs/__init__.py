"""Batched TorchRL environments (batch size ``[tasks, episodes]``) whose task identifiers are
set under ``"params"`` (:data:`armeta_rl.tasks.TASK_KEY`) in the reset TensorDict and kept across
automatic resets; every env tells its box (``env.task_space``) and p0 (``env.p0``), and so do
the drop-ins for TorchRL's wrappers (:class:`TaskTransformedEnv`, :class:`TaskSerialEnv`,
:class:`TaskParallelEnv`; :func:`task_space` reads it through any layout).

All are imported eagerly: ``torchrl.envs`` already imports MuJoCo, so the MuJoCo envs add no
measurable start-up time.
"""

from armeta_rl.envs.acrobot import AcrobotEnv
from armeta_rl.envs.ant_goal import AntGoalEnv
from armeta_rl.envs.identified_env import IdentifiedSystemEnv
from armeta_rl.envs.locomotion import (
    AntDirEnv,
    HalfCheetahDirEnv,
    HalfCheetahVelEnv,
    Walker2dVelEnv,
)
from armeta_rl.envs.pendulum import PendulumEnv
from armeta_rl.envs.point_navigation import PointNavigationEnv
from armeta_rl.envs.task_env import (
    TaskParallelEnv,
    TaskSerialEnv,
    TaskTransformedEnv,
    identifier_check,
    task_space,
)

__all__ = [
    "AcrobotEnv",
    "AntDirEnv",
    "AntGoalEnv",
    "HalfCheetahDirEnv",
    "HalfCheetahVelEnv",
    "IdentifiedSystemEnv",
    "PendulumEnv",
    "PointNavigationEnv",
    "TaskParallelEnv",
    "TaskSerialEnv",
    "TaskTransformedEnv",
    "Walker2dVelEnv",
    "identifier_check",
    "task_space",
]
