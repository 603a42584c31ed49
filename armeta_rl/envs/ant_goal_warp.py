"""Ant goal-position on MuJoCo Warp: the :class:`~armeta_rl.envs.ant_goal.AntGoalEnv` task (same
MJCF, reward, termination, observation, seeding) with its physics on a warp device, a GPU where
there is one (issue "Scale: GPUs and distributed collection", item 3), and everything else of a
step there too: nothing goes through the host between steps.

The physics is the one every family shares on MuJoCo Warp
(:mod:`armeta_rl.envs.warp_physics`): :class:`~armeta_rl.envs.warp_physics.WarpBatch` stands in
for the CPU env's ``mujoco.batch.Batch``, and the env computes its observation, reward and
termination with the CPU env's own code (:class:`~armeta_rl.envs.ant_goal.AntTaskEnv`) in torch
on the warp device. Each step runs the physics steps, then ``mjw.forward`` at the new state, whose
sensor stage (the torso accelerometer of :func:`~armeta_rl.envs.ant_goal.load_ant_model`)
computes the contact forces ``cfrc_ext``, as the CPU batch does with ``stage=mjSTAGE_ACC``.

MuJoCo Warp computes in float32 (the CPU env in float64) and solves contacts with its own
parallel solver, so its trajectories equal the CPU dynamics only up to a tolerance, stated and
checked in ``tests/test_ant_goal_warp.py``. ``mujoco-warp`` is an optional dependency
(``pip install 'armeta-rl[gpu]'``).
"""

from __future__ import annotations

from collections.abc import Callable

from armeta_rl.envs.ant_goal import AntGoalEnv
from armeta_rl.envs.warp_physics import WarpSimulation, warp_env


class AntGoalWarpEnv(WarpSimulation, AntGoalEnv):
    """:class:`~armeta_rl.envs.ant_goal.AntGoalEnv` with its simulations on MuJoCo Warp and its
    step on the warp device.

    Arguments: :class:`~armeta_rl.envs.ant_goal.AntGoalEnv`'s, passed on unchanged, and
    ``warp_device``, ``nconmax``, ``njmax``, ``graphs``
    (:class:`~armeta_rl.envs.warp_physics.WarpSimulation`).
    """


def ant_goal_warp(warp_device: str = "cuda", **kwargs) -> Callable[..., AntGoalWarpEnv]:
    """``AntGoalWarpEnv`` with ``kwargs`` as a ``make_env`` for the episode collectors, once
    ``warp_device`` is checked (:func:`~armeta_rl.envs.warp_physics.warp_env`)."""
    return warp_env(AntGoalWarpEnv, warp_device, **kwargs)
