"""A run's players (task space, p0, leader, principle, evaluation collector): built from its
config, or rebuilt from a saved run directory with its latest checkpoint."""

from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.config import load_run_config
from armeta_rl.errors import ConfigError
from armeta_rl.factory import (
    build_collector,
    build_initial,
    build_leader,
    build_principle,
    build_space,
)
from armeta_rl.learners.base import Leader
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.tasks import TaskDistribution, TaskSpace
from armeta_rl.trainers.checkpoint import RunCheckpoint


@dataclass
class Players:
    """Everything a run trains and evaluates."""

    space: TaskSpace
    initial: TaskDistribution
    leader: Leader
    principle: RiskPrinciple
    eval_collector: TaskCollector

    @property
    def adversary(self) -> TaskDistribution | None:
        """The learned task distribution p_φ, for principles that have one."""
        return getattr(self.principle, "adversary", None)


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (CPU and any accelerator)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def build_players(cfg: DictConfig) -> Players:
    """Seed, then build the players of ``cfg`` (the seed fixes their initial parameters)."""
    seed_everything(cfg.seed)
    space = build_space(cfg)
    initial = build_initial(cfg, space)
    collector = build_collector(cfg, "benchmark.collector")
    eval_collector = build_collector(cfg, "benchmark.eval_collector")
    leader = build_leader(cfg, collector)
    principle = build_principle(cfg, space, initial)
    return Players(space, initial, leader, principle, eval_collector)


def load_players(run_dir: str | Path, key: str) -> tuple[DictConfig, Players]:
    """Rebuild a saved run's players and load its latest checkpoint."""
    cfg = load_run_config(run_dir, key)
    players = build_players(cfg)
    checkpoint = RunCheckpoint(Path(run_dir) / "checkpoints", players.leader, players.principle)
    if not checkpoint.checkpoints():
        raise ConfigError(key, str(run_dir), "has no checkpoint")
    checkpoint.restore(key, ("leader", "principle"), fallback=False)
    return cfg, players
