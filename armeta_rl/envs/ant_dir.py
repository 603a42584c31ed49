"""The Ant-Dir family's former module: :class:`~armeta_rl.envs.locomotion.AntDirEnv` lives with
the other locomotion envs; this name stays so that the ``_target_`` of run configs saved before
(``armeta_rl.envs.ant_dir.AntDirEnv``) still loads."""

from armeta_rl.envs.locomotion import AntDirEnv

__all__ = ["AntDirEnv"]
