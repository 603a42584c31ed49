"""Ant-Dir: the MuJoCo Ant must run in a hidden direction of the plane (ProMP's
``AntRandDirec2DEnv``, Rothfuss et al. 2018, as learn2learn's ``AntDirectionEnv``), batched over
``[tasks, episodes]``.

The task is an angle θ (identifier ``direction_angle``, radians, any finite value; the references
draw the direction uniformly on the unit circle, i.e. θ ~ U[-π, π]) and its direction
``u = (cos θ, sin θ)``. The reward of a step, with ``Δxy`` the torso's displacement over the step,
``dt = frame_skip · 0.01 s``, ``a`` the action as given and ``F = clip(cfrc_ext, -1, 1)``, is the
references':

    r = u · Δxy / dt                           velocity along the direction
        - ctrl_cost_weight · ‖a‖²              default 0.5 (ProMP / learn2learn)
        - contact_cost_weight · ‖F‖²           default 0.0005 (= 0.5·1e-3)
        + survive_reward                       default 1.0, every step

and an episode terminates when the state is non-finite or the torso height leaves
``healthy_z_range`` = [0, 1] (the references' ``1.0 >= z >= 0``). The references take ``Δxy``
from the torso's ``xpos`` read right after each ``mj_step`` (the start of its last substep); here
it is the exact displacement of the torso, whose free joint makes ``xpos = qpos[0:3]``.

Model, dynamics, observation (119 values, torso position included; ProMP's leaves out
``qpos[0:2]``, the xmat and the xpos) and throughput are those of the Ant of
:class:`~armeta_rl.envs.ant_goal.AntTaskEnv`; pytorch-maml-rl's Ant-Dir is the 1-D case
(θ ∈ {0, π}) with its Ant-Pos weights.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from armeta_rl.envs.ant_goal import AntTaskEnv


class AntDirEnv(AntTaskEnv):
    """MuJoCo Ant running in the direction ``direction_angle``, batch size ``[tasks, episodes]``;
    see the module docstring.

    Args:
        batch_size: ``[tasks, episodes]`` (any batch shape works).
        max_steps: time limit in env steps (200).
        frame_skip: physics steps per env step (5, as gymnasium's Ant).
        ctrl_cost_weight: weight of the control cost (module docstring).
        contact_cost_weight: weight of the contact cost (module docstring).
        survive_reward: reward per step alive (module docstring).
        healthy_z_range: torso heights outside this closed interval terminate the episode.
        reset_noise_scale: initial qpos = model qpos0 + U(±scale), qvel = scale·N(0, 1).
        threads: threads stepping the MuJoCo batch natively (1: the calling thread only;
            ``None``: one per CPU core).
        seed: seed of the generator for reset noise and default angles (U[-π, π]).
        device: torch device of the outputs (the physics runs on the CPU).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import AntDirEnv
        >>> from armeta_rl.tasks import TASK_KEY, reset_with_identifiers
        >>> env = AntDirEnv(batch_size=(2, 3), seed=0)  # 2 tasks x 3 episodes
        >>> task = torch.tensor([1.57]).expand(2, 3, -1)  # direction (radians)
        >>> start = reset_with_identifiers(env, TensorDict({TASK_KEY: task}, [2, 3]))
        >>> steps = env.rollout(4, tensordict=start, auto_reset=False)
        >>> steps["observation"].shape, bool((steps[TASK_KEY] == task[:, :, None]).all())
        (torch.Size([2, 3, 4, 119]), True)
    """

    identifier_names = ("direction_angle",)

    def __init__(
        self,
        batch_size: Sequence[int] = (1, 1),
        max_steps: int = 200,
        frame_skip: int = 5,
        ctrl_cost_weight: float = 0.5,
        contact_cost_weight: float = 5e-4,
        survive_reward: float = 1.0,
        healthy_z_range: Sequence[float] = (0.0, 1.0),
        reset_noise_scale: float = 0.1,
        threads: int | None = 1,
        seed: int | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        super().__init__(batch_size, max_steps, frame_skip, ctrl_cost_weight, contact_cost_weight,
                         survive_reward, healthy_z_range, reset_noise_scale, threads, seed, device)

    def _default_identifiers(self) -> torch.Tensor:
        unit = torch.rand(*self.batch_size, 1, generator=self._generator, dtype=torch.float64)
        return torch.pi * (2 * unit - 1)

    def _reward(self, action: np.ndarray, qpos_before: np.ndarray,
                task: np.ndarray) -> np.ndarray:
        """The Ant-Dir reward of the module docstring."""
        direction = np.stack([np.cos(task[:, 0]), np.sin(task[:, 0])], -1)
        velocity = (self._qpos[:, :2] - qpos_before[:, :2]) / self.dt
        return self.ant_reward((direction * velocity).sum(-1), action)
