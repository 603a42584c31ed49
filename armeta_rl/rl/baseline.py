"""Linear feature baseline and GAE advantages for MAML-TRPO (MAML paper, Sec. 5.3; Duan et al.
2016's linear feature baseline, as in pytorch-maml-rl), batched over tasks.

Trajectories are TensorDicts ``[K, episodes, T]`` from
:class:`~armeta_rl.collectors.episodes.PointNavigationCollector` (``"observation"``,
``"reward"``, ``"done"``, ``"mask"``). The time limit ends an episode's return (the task is a
finite-horizon MDP and the baseline sees the time step), so truncation is treated as termination.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.objectives.value.functional import generalized_advantage_estimate


def discounted_returns(trajectories: TensorDictBase, gamma: float) -> Tensor:
    """Discounted reward-to-go ``[K, E, T, 1]`` within each episode (zero after its end).

    With λ = 1 and zero values, GAE's advantage is exactly Σ_{l≥0} γ^l r_{t+l} up to the episode's
    end, so torchrl's ``generalized_advantage_estimate`` computes it.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.rl.baseline import discounted_returns
        >>> done = torch.tensor([False, False, True]).reshape(1, 1, 3, 1)
        >>> steps = TensorDict({"reward": torch.ones(1, 1, 3, 1), "done": done,
        ...                     "mask": torch.ones(1, 1, 3).bool()}, [1, 1, 3])  # 1 episode
        >>> discounted_returns(steps, gamma=0.5).flatten()
        tensor([1.7500, 1.5000, 1.0000])
    """
    reward = trajectories["reward"] * trajectories["mask"].unsqueeze(-1)
    done = trajectories["done"]
    zeros = torch.zeros_like(reward)
    returns, _ = generalized_advantage_estimate(gamma, 1.0, zeros, zeros, reward, done, done)
    return returns


def baseline_features(trajectories: TensorDictBase) -> Tensor:
    """Features ``[K, E, T, 2·obs_dim + 4]``: [s, s², t/100, (t/100)², (t/100)³, 1], zero on
    masked steps.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.rl.baseline import baseline_features
        >>> observation = torch.tensor([0.5, -2.0]).expand(1, 1, 4, 2)  # s at t = 0, ..., 3
        >>> steps = TensorDict({"observation": observation,
        ...                     "mask": torch.ones(1, 1, 4).bool()}, [1, 1, 4])
        >>> baseline_features(steps)[0, 0, 3]  # t = 3: s, s², 0.03, 0.03², 0.03³, 1
        tensor([ 5.0000e-01, -2.0000e+00,  2.5000e-01,  4.0000e+00,  3.0000e-02,
                 9.0000e-04,  2.7000e-05,  1.0000e+00])
    """
    observation = trajectories["observation"]
    mask = trajectories["mask"].unsqueeze(-1).to(observation.dtype)
    steps = trajectories.batch_size[-1]
    time = torch.arange(steps, dtype=observation.dtype, device=observation.device) / 100.0
    time = time.view(*([1] * (observation.dim() - 2)), steps, 1).expand(*observation.shape[:-1], 1)
    features = torch.cat(
        [observation, observation**2, time, time**2, time**3, torch.ones_like(time)], dim=-1
    )
    return features * mask


def fit_linear_baseline(features: Tensor, targets: Tensor, reg: float = 1e-5) -> Tensor:
    """Per-task ridge regression (Duan et al. 2016's linear feature baseline): coefficients
    ``[K, f]`` minimizing
    ‖X_k c_k − y_k‖² + reg‖c_k‖² for features ``[K, ..., f]`` and targets ``[K, ...]``.

    Solves the normal equations (X_kᵀX_k + reg·I) c_k = X_kᵀ y_k for all tasks at once with
    ``torch.linalg.solve`` on ``[K, f, f]`` (in float64).

    Examples:
        >>> import torch
        >>> from armeta_rl.rl.baseline import fit_linear_baseline
        >>> features = torch.tensor([[[1.0], [2.0], [3.0]]])  # [K=1, 3 points, 1 feature]
        >>> fit_linear_baseline(features, targets=2 * features[..., 0], reg=0.0)
        tensor([[2.]])
    """
    n_tasks, n_features = features.shape[0], features.shape[-1]
    design = features.reshape(n_tasks, -1, n_features).double()
    target = targets.reshape(n_tasks, -1, 1).double()
    gram = design.transpose(1, 2) @ design
    eye = torch.eye(n_features, dtype=gram.dtype, device=gram.device)
    coefficients = torch.linalg.solve(gram + reg * eye, design.transpose(1, 2) @ target)
    return coefficients.squeeze(-1).to(features.dtype)


def baseline_values(trajectories: TensorDictBase, gamma: float, reg: float = 1e-5) -> Tensor:
    """Values ``[K, E, T, 1]`` of the linear baseline refit on each task's own episodes.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.rl.baseline import baseline_values
        >>> reward = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]).reshape(1, 2, 3, 1)
        >>> done = torch.tensor([False, False, True]).expand(1, 2, 3).unsqueeze(-1)
        >>> def episodes(observation):  # one task, two 3-step episodes, returns 1 and 0
        ...     return TensorDict({"observation": observation, "reward": reward, "done": done,
        ...                        "mask": torch.ones(1, 2, 3).bool()}, [1, 2, 3])
        >>> same = torch.zeros(1, 2, 3, 2)  # the states do not tell the episodes apart
        >>> baseline_values(episodes(same), gamma=1.0).flatten()  # the mean return, 0.5
        tensor([0.5000, 0.5000, 0.5000, 0.5000, 0.5000, 0.5000])
        >>> apart = torch.tensor([[1.0, 0.0], [0.0, 0.0]]).reshape(1, 2, 1, 2).expand(1, 2, 3, 2)
        >>> values = baseline_values(episodes(apart), gamma=1.0)  # each episode's own return
        >>> values.flatten().round(decimals=3)  # up to the ridge's 1e-5
        tensor([1., 1., 1., 0., 0., 0.])
    """
    features = baseline_features(trajectories)
    coefficients = fit_linear_baseline(features, discounted_returns(trajectories, gamma), reg)
    flat = features.reshape(features.shape[0], -1, features.shape[-1])
    values = (flat @ coefficients.unsqueeze(-1)).reshape(*features.shape[:-1], 1)
    return values


def episode_mean(values: Tensor, mask: Tensor) -> Tensor:
    """Per-task mean ``[K]`` over episodes of each episode's time-average over its valid steps
    (pytorch-maml-rl's ``weighted_mean``); ``values`` and ``mask`` are ``[K, E, T]``.

    Examples:
        >>> import torch
        >>> from armeta_rl.rl.baseline import episode_mean
        >>> values = torch.tensor([[[1.0, 2.0, 3.0], [4.0, 9.0, 9.0]]])
        >>> mask = torch.tensor([[[True, True, True], [True, False, False]]])
        >>> episode_mean(values, mask)  # the mean of the episodes' means, 2 and 4
        tensor([3.])
    """
    weights = mask.to(values.dtype)
    per_episode = (values * weights).sum(-1) / weights.sum(-1).clamp_min(1.0)
    return per_episode.mean(-1)


def normalize_per_task(advantages: Tensor, mask: Tensor, eps: float = 1e-8) -> Tensor:
    """(A − m_k)/(s_k + eps) per task, zero on masked steps, with m_k and s_k² the
    :func:`episode_mean` of A and of (A − m_k)² (pytorch-maml-rl's ``weighted_normalize``).

    The statistics weigh episodes equally, as the losses do: an episode that reaches its goal after
    a few steps has few, large advantages, and each of its steps weighs 1/length in the losses. In
    the statistics they weigh as much, so they widen s_k and stay bounded (|Â| ≤ √E for one step
    standing alone), whereas statistics pooled over steps would barely see them and let such an
    episode dominate the inner step.

    ``advantages`` ``[K, E, T]`` and bool ``mask`` ``[K, E, T]``.

    Examples:
        >>> import torch
        >>> from armeta_rl.rl.baseline import normalize_per_task
        >>> normalize_per_task(torch.tensor([[[1.0, 2.0, 3.0]]]), torch.ones(1, 1, 3).bool())
        tensor([[[-1.2247,  0.0000,  1.2247]]])
    """
    weights = mask.to(advantages.dtype)
    mean = episode_mean(advantages, mask)[:, None, None]
    variance = episode_mean((advantages - mean) ** 2, mask)[:, None, None]
    return (advantages - mean) / (variance.sqrt() + eps) * weights


def gae_advantages(trajectories: TensorDictBase, gamma: float = 0.99, lmbda: float = 1.0,
                   reg: float = 1e-5) -> Tensor:
    """Normalized GAE advantages ``[K, E, T]`` with the per-task linear baseline (ridge ``reg``)
    as V: Â_t = Σ_l (γλ)^l δ_{t+l}, δ_t = r_t + γV(s_{t+1}) − V(s_t) (Schulman et al. 2016, GAE
    Eq. (16)), then :func:`normalize_per_task`.

    torchrl's ``generalized_advantage_estimate`` with V(s_t) from the baseline, V(s_{t+1}) the
    next step's value, and episodes ending at ``done`` (goal reached or time limit).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.rl.baseline import gae_advantages
        >>> reward = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]).reshape(1, 2, 3, 1)
        >>> done = torch.tensor([False, False, True]).expand(1, 2, 3).unsqueeze(-1)
        >>> steps = TensorDict({"observation": torch.zeros(1, 2, 3, 2), "reward": reward,
        ...                     "done": done, "mask": torch.ones(1, 2, 3).bool()}, [1, 2, 3])
        >>> # γ = 1: V = 0.5 everywhere (the mean return), so δ = (0, 0, ±0.5) and with λ = 0.5
        >>> # Â = ±(0.125, 0.25, 0.5); normalized by their spread √((0.125² + 0.25² + 0.5²)/3)
        >>> gae_advantages(steps, gamma=1.0, lmbda=0.5)
        tensor([[[ 0.3780,  0.7559,  1.5119],
                 [-0.3780, -0.7559, -1.5119]]])
    """
    mask = trajectories["mask"]
    values = baseline_values(trajectories, gamma, reg) * mask.unsqueeze(-1)
    next_values = torch.cat([values[..., 1:, :], torch.zeros_like(values[..., :1, :])], dim=-2)
    reward = trajectories["reward"] * mask.unsqueeze(-1)
    done = trajectories["done"]
    advantages, _ = generalized_advantage_estimate(
        gamma, lmbda, values, next_values, reward, done, done
    )
    return normalize_per_task(advantages.squeeze(-1), mask)
