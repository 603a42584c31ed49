"""The locomotion families on MuJoCo Warp: :mod:`armeta_rl.envs.locomotion`'s envs with their
simulations as warp worlds (:class:`~armeta_rl.envs.warp_physics.WarpSimulation`). Each is its
CPU family (model, reward, observation, termination, identifiers, seeding: the family's own code,
run in torch on the warp device) with the physics of MuJoCo Warp; the mass-scale families
(HalfCheetah-MassVel, Walker2d-MassVel) are the Vel envs under a
:class:`~armeta_rl.envs.mujoco_tasks.PhysicsTaskTransform`, which writes each simulation's masses
into its own world (``configs/benchmark/*_warp.yaml``). Arguments: the CPU env's, plus
``warp_device``, ``nconmax``, ``njmax``, ``graphs``
(:class:`~armeta_rl.envs.warp_physics.WarpSimulation`): for instance
``HalfCheetahVelWarpEnv(batch_size=(40, 20), warp_device="cuda")``, whose ``reset`` and ``step``
take and return tensors on that GPU.
"""

from armeta_rl.envs.batched_mujoco import STAGE_POS
from armeta_rl.envs.locomotion import (
    AntDirEnv,
    HalfCheetahDirEnv,
    HalfCheetahVelEnv,
    Walker2dVelEnv,
)
from armeta_rl.envs.warp_physics import WarpSimulation


class HalfCheetahVelWarpEnv(WarpSimulation, HalfCheetahVelEnv):
    """:class:`~armeta_rl.envs.locomotion.HalfCheetahVelEnv` on MuJoCo Warp."""

    stage, torso_from_qpos = STAGE_POS, False  # the torso from the warp kinematics


class HalfCheetahDirWarpEnv(WarpSimulation, HalfCheetahDirEnv):
    """:class:`~armeta_rl.envs.locomotion.HalfCheetahDirEnv` on MuJoCo Warp."""

    stage, torso_from_qpos = STAGE_POS, False  # the torso from the warp kinematics


class Walker2dVelWarpEnv(WarpSimulation, Walker2dVelEnv):
    """:class:`~armeta_rl.envs.locomotion.Walker2dVelEnv` on MuJoCo Warp."""

    stage, torso_from_qpos = STAGE_POS, False  # the torso from the warp kinematics


class AntDirWarpEnv(WarpSimulation, AntDirEnv):
    """:class:`~armeta_rl.envs.locomotion.AntDirEnv` on MuJoCo Warp."""
