"""Run directories: their lock, building a run's players from its config and restoring them from
disk.

A run directory holds ``run.lock``, ``config.yaml`` (the resolved config), ``checkpoints/``,
``logs/``, ``eval.json`` and ``density.png``.
"""

from __future__ import annotations

import errno
import fcntl
import os
import random
from collections.abc import Iterator
from contextlib import contextmanager
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

LOCK_FILE = "run.lock"


def check_run_dir(run_dir: Path, key: str) -> None:
    """Refuse, before anything is written, a run directory that is an existing file, or that
    cannot be created or written (a read-only file system or directory)."""
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(key, str(run_dir), "is an existing file, not a directory")
    existing = next(p for p in (run_dir, *run_dir.parents) if p.exists())
    if not existing.is_dir():
        raise ConfigError(key, str(run_dir), f"cannot be created: {existing} is a file")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(key, str(run_dir), f"cannot be written: {existing} is read-only")


@contextmanager
def run_lock(run_dir: Path, key: str) -> Iterator[Path]:
    """Hold an exclusive lock on ``run_dir`` (``fcntl.flock`` on ``run.lock``, which names the
    holder's pid) for the ``with`` block, creating the directory.

    The kernel releases the lock when its holder exits, however it exits, so a lock left by a dead
    process is taken over. Taking a lock this process already holds is a no-op (the CLI locks the
    run directory before Hydra writes to it, and the run locks it again).

    Raises:
        ConfigError: naming ``key``, if another live process holds the lock.
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as error:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
        os.close(fd)
        if error.errno not in (errno.EWOULDBLOCK, errno.EACCES):
            raise
        if holder == str(os.getpid()):
            yield path
            return
        raise ConfigError(
            key, str(run_dir),
            f"is in use by another run (pid {holder or '?'}): wait for it to end or choose "
            "another directory",
        ) from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield path
    finally:
        os.close(fd)


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
