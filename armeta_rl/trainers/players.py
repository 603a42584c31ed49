"""A run's players (task space, p0, leader, principle, evaluation collector): built from its
config, or rebuilt from a saved run directory with its latest checkpoint."""

from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.collectors.episodes import EpisodeCollector
from armeta_rl.config import TrainConfig, load_run, run_values
from armeta_rl.devices import CPU
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
from armeta_rl.trainers.checkpoint import RunCheckpoint, run_identity, saved_identity
from armeta_rl.trainers.run_dir import check_contents


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
    device (``config.torch_device``; the seed fixes their initial parameters, which are drawn on
    the CPU whatever the device)."""
    device = config.torch_device
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


def _leaves(values: dict[str, Any], name: str) -> dict[str, object]:
    """The values below dotted ``name`` in the nested ``values``, by dotted key (``name`` itself
    if a leaf)."""
    value: Any = values
    for part in name.split("."):
        value = value.get(part) if isinstance(value, dict) else None
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


def load_frozen_leader(config: TrainConfig, players: Players) -> None:
    """Load the final leader of the finished run ``config.trainer.frozen_leader`` into
    ``players.leader`` (an attack run: the adversary trains against that learner, whose θ stays).

    Raises:
        ConfigError: naming ``trainer.frozen_leader``, if the method has no flow adversary, the
            directory is not a finished run (no ``eval.json``), a benchmark or learner setting
            that both runs have differs, or its checkpoint is broken or does not fit.
    """
    source = config.trainer.frozen_leader
    if players.adversary is None:
        raise ConfigError(
            FROZEN_KEY, source,
            f"needs a method with a flow adversary (ar_*), not {config.method.name}",
        )
    saved = run_values(source, FROZEN_KEY)
    if not (Path(source) / "eval.json").is_file():
        raise ConfigError(FROZEN_KEY, source, "has not finished (no eval.json)")
    names = ("benchmark", "method.learner", "learner")
    values = config.values()
    theirs = {k: v for name in names for k, v in _leaves(saved, name).items()}
    ours = {k: v for name in names for k, v in _leaves(values, name).items()}
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
    check_contents(Path(source), FROZEN_KEY)
    checkpoint = RunCheckpoint(Path(source) / "checkpoints", players.leader, players.principle,
                               device=players.device, identity=run_identity(saved),
                               adopt=config.adopt, accepts=[saved_identity(source)])
    checkpoint.restore(FROZEN_KEY, ("leader",), fallback=False)


def saved_run(run_dir: str | Path, key: str, device: str | None = None,
              changes: dict | None = None) -> TrainConfig:
    """A saved run's config (:func:`armeta_rl.config.load_run`) to rebuild its players on
    ``device`` (default: the run's own ``device``) with ``changes`` (e.g. other ``eval``
    settings). Its ``threads`` (training's torch threads, at most the CPUs of the machine that
    trained it) is set to 1: loading and evaluating use none of them."""
    return load_run(run_dir, key, {"threads": 1, **(changes or {}),
                                   **({} if device is None else {"device": device})})


def restore_players(run_dir: str | Path, key: str, config: TrainConfig) -> Players:
    """The players of ``config`` (:func:`saved_run`) with the latest checkpoint of ``run_dir``
    loaded onto its device, wherever it was saved."""
    check_contents(Path(run_dir), key)
    players = build_players(config)
    checkpoint = RunCheckpoint(Path(run_dir) / "checkpoints", players.leader, players.principle,
                               device=players.device, identity=run_identity(config.values()),
                               adopt=config.adopt, accepts=[saved_identity(run_dir)])
    if not checkpoint.checkpoints():
        raise ConfigError(key, str(run_dir), "has no checkpoint")
    checkpoint.restore(key, ("leader", "principle"), fallback=False)
    return players


def load_players(
    run_dir: str | Path, key: str, device: str | None = None, changes: dict | None = None
) -> tuple[TrainConfig, Players]:
    """A saved run's config (:func:`saved_run`) and its players with its latest checkpoint
    (:func:`restore_players`)."""
    config = saved_run(run_dir, key, device, changes)
    return config, restore_players(run_dir, key, config)
