"""A run's players (task space, p0, leader, principle, evaluation collector): built from its
config, or rebuilt from a saved run directory with its latest checkpoint."""

from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.collectors.episodes import EpisodeCollector
from armeta_rl.config import TrainConfig, load_run_config, validate
from armeta_rl.devices import CPU, resolve_device
from armeta_rl.errors import ConfigError
from armeta_rl.factory import (
    build_collector,
    build_initial,
    build_leader,
    build_principle,
    build_space,
)
from armeta_rl.fields import config_error
from armeta_rl.learners.base import Leader
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.tasks import TaskDistribution, TaskSpace
from armeta_rl.trainers.checkpoint import RunCheckpoint, run_identity


@dataclass
class Players:
    """Everything a run trains and evaluates, and the device they compute on."""

    space: TaskSpace
    initial: TaskDistribution
    leader: Leader
    principle: RiskPrinciple
    eval_collector: TaskCollector
    device: torch.device = CPU

    @property
    def adversary(self) -> TaskDistribution | None:
        """The learned task distribution p_φ, for principles that have one."""
        return getattr(self.principle, "adversary", None)


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (CPU and any accelerator)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def build_players(config: TrainConfig) -> Players:
    """Seed, then build the players of ``config`` (:func:`armeta_rl.config.validate`) on its
    ``device`` (the seed fixes their initial parameters, which are drawn on the CPU whatever the
    device)."""
    device = resolve_device(config.device)
    seed_everything(config.seed)
    benchmark, method = config.benchmark, config.method
    space = build_space(benchmark.space)
    initial = build_initial(benchmark.initial, space, device)
    collector = build_collector(benchmark.collector, "benchmark.collector", space, device)
    eval_collector = build_collector(benchmark.eval_collector, "benchmark.eval_collector", space,
                                     device)
    if config.eval.support_noise > 0 and isinstance(eval_collector, EpisodeCollector):
        raise ConfigError(
            "eval.support_noise", config.eval.support_noise,
            f"must be 0 on {benchmark.name}: its tasks are adapted from episodes, which have "
            "no support labels to perturb",
        )
    leader = build_leader(method, config.learner, collector, benchmark.model, device)
    principle = build_principle(method, config.risk, space, initial, config.trainer.iterations,
                                device, collector)
    return Players(space, initial, leader, principle, eval_collector, device)


FROZEN_KEY = "trainer.frozen_leader"
SAME_MATHS = ("compile", "adaptation")
"""Learner keys that choose how the same maths is computed: they may differ between a frozen
learner's run and the run attacking it."""


def _leaves(cfg: DictConfig, name: str) -> dict[str, object]:
    """The resolved values below ``name`` in ``cfg``, by dotted key (``name`` itself if a leaf)."""
    node = OmegaConf.select(cfg, name)
    value = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node
    if not isinstance(value, dict):
        return {name: value}
    found: dict[str, object] = {}
    stack = [(name, value)]
    while stack:
        prefix, items = stack.pop()
        for key, item in items.items():
            if isinstance(item, dict):
                stack.append((f"{prefix}.{key}", item))
            else:
                found[f"{prefix}.{key}"] = item
    return found


def load_frozen_leader(cfg: DictConfig, players: Players) -> None:
    """Load the final leader of the finished run ``cfg.trainer.frozen_leader`` into
    ``players.leader`` (an attack run: the adversary trains against that learner, whose θ stays).

    Raises:
        ConfigError: naming ``trainer.frozen_leader``, if the method has no flow adversary, the
            directory is not a finished run (no ``eval.json``), a benchmark or learner setting
            that both runs have differs, or its checkpoint is broken or does not fit.
    """
    source = cfg.trainer.frozen_leader
    if players.adversary is None:
        raise ConfigError(
            FROZEN_KEY, source,
            f"needs a method with a flow adversary (ar_*), not {cfg.method.name}",
        )
    saved = load_run_config(source, FROZEN_KEY)
    if not (Path(source) / "eval.json").is_file():
        raise ConfigError(FROZEN_KEY, source, "has not finished (no eval.json)")
    names = ("benchmark", "method.learner", "learner")
    theirs = {k: v for name in names for k, v in _leaves(saved, name).items()}
    ours = {k: v for name in names for k, v in _leaves(cfg, name).items()}
    # only the keys both configs have are compared; a real mismatch of shapes fails the load
    differing = sorted(k for k in theirs.keys() & ours.keys()
                       if theirs.get(k) != ours.get(k) and k.rsplit(".", 1)[-1] not in SAME_MATHS)
    if differing:
        first = differing[0]
        raise ConfigError(
            FROZEN_KEY, source,
            f"its {first} = {theirs.get(first)!r} differs from this run's {ours.get(first)!r}: "
            "the learner attacked must have this run's benchmark and learner settings",
        )
    checkpoint = RunCheckpoint(Path(source) / "checkpoints", players.leader, players.principle,
                               device=players.device, identity=run_identity(saved))
    checkpoint.restore(FROZEN_KEY, ("leader",), fallback=False)


def load_players(
    run_dir: str | Path, key: str, device: str | None = None, changes: dict | None = None
) -> tuple[TrainConfig, Players]:
    """Rebuild a saved run's players on ``device`` (default: the run's own ``device``), with
    ``changes`` to its config (e.g. other ``eval`` settings), and load its latest checkpoint
    there, wherever it was saved. Its ``threads`` (training's torch threads, at most the CPUs
    of the machine that trained it) is set to 1: loading and evaluating use none of them."""
    try:
        cfg = OmegaConf.merge(load_run_config(run_dir, key), {"threads": 1}, changes or {},
                              {} if device is None else {"device": device})
    except OmegaConfBaseException as error:
        raise config_error(error) from None
    config = validate(cfg)
    players = build_players(config)
    checkpoint = RunCheckpoint(Path(run_dir) / "checkpoints", players.leader, players.principle,
                               device=players.device, identity=run_identity(cfg))
    if not checkpoint.checkpoints():
        raise ConfigError(key, str(run_dir), "has no checkpoint")
    checkpoint.restore(key, ("leader", "principle"), fallback=False)
    return config, players
