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
    """
    reward = trajectories["reward"] * trajectories["mask"].unsqueeze(-1)
    done = trajectories["done"]
    zeros = torch.zeros_like(reward)
    returns, _ = generalized_advantage_estimate(gamma, 1.0, zeros, zeros, reward, done, done)
    return returns


def baseline_features(trajectories: TensorDictBase) -> Tensor:
    """Features ``[K, E, T, 2·obs_dim + 4]``: [s, s², t/100, (t/100)², (t/100)³, 1], zero on
    masked steps."""
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
    """
    n_tasks, n_features = features.shape[0], features.shape[-1]
    design = features.reshape(n_tasks, -1, n_features).double()
    target = targets.reshape(n_tasks, -1, 1).double()
    gram = design.transpose(1, 2) @ design
    eye = torch.eye(n_features, dtype=gram.dtype, device=gram.device)
    coefficients = torch.linalg.solve(gram + reg * eye, design.transpose(1, 2) @ target)
    return coefficients.squeeze(-1).to(features.dtype)


def baseline_values(trajectories: TensorDictBase, gamma: float, reg: float = 1e-5) -> Tensor:
    """Values ``[K, E, T, 1]`` of the linear baseline refit on each task's own episodes."""
    features = baseline_features(trajectories)
    coefficients = fit_linear_baseline(features, discounted_returns(trajectories, gamma), reg)
    flat = features.reshape(features.shape[0], -1, features.shape[-1])
    values = (flat @ coefficients.unsqueeze(-1)).reshape(*features.shape[:-1], 1)
    return values


def episode_mean(values: Tensor, mask: Tensor) -> Tensor:
    """Per-task mean ``[K]`` over episodes of each episode's time-average over its valid steps
    (pytorch-maml-rl's ``weighted_mean``); ``values`` and ``mask`` are ``[K, E, T]``."""
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
