"""Run configs: checks of user-facing values (so bad input fails with one line before any work
starts) and loading the resolved config a run directory keeps."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from armeta_rl.errors import ConfigError

_MISSING = object()
CONFIG_FILE = "config.yaml"


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return (_is_int(value) or isinstance(value, float)) and math.isfinite(value)


def _positive_int(value: Any) -> bool:
    return _is_int(value) and value >= 1


def _fractions(value: Any) -> bool:
    return (
        isinstance(value, (list, tuple))
        and len(value) > 0
        and all(_is_number(a) and 0.0 < a < 1.0 for a in value)
    )


CHECKS: tuple[tuple[str, Callable[[Any], bool], str], ...] = (
    ("seed", _is_int, "must be an integer"),
    ("threads", _positive_int, "must be an integer >= 1"),
    ("trainer.iterations", _positive_int, "must be an integer >= 1"),
    ("trainer.meta_batch", _positive_int, "must be an integer >= 1"),
    ("trainer.log_every", _positive_int, "must be an integer >= 1"),
    ("trainer.checkpoint_every", _positive_int, "must be an integer >= 1"),
    ("trainer.stop_at", lambda v: v is None or _positive_int(v), "must be null or an integer >= 1"),
    ("trainer.density_every", lambda v: _is_int(v) and v >= 0,
     "must be an integer >= 0 (0: no density frames)"),
    ("eval.n_tasks", _positive_int, "must be an integer >= 1"),
    ("eval.alphas", _fractions, "must be a non-empty list of numbers in (0, 1)"),
    ("eval.seed", _is_int, "must be an integer"),
    ("eval.support_noise", lambda v: _is_number(v) and v >= 0, "must be a number >= 0"),
    ("risk.ar.lam", lambda v: _is_number(v) and v >= 0, "must be a number >= 0 (λ ≥ 0)"),
    ("risk.ar.update_every", _positive_int, "must be an integer >= 1"),
    ("risk.ar.lr", lambda v: _is_number(v) and v > 0, "must be a number > 0"),
    ("risk.dr.alpha", lambda v: _is_number(v) and 0 < v < 1, "must be a number in (0, 1)"),
    ("learner.maml.inner_lr", lambda v: _is_number(v) and v > 0, "must be a number > 0"),
    ("learner.maml.inner_steps", _positive_int, "must be an integer >= 1"),
    ("learner.maml.outer_lr", lambda v: _is_number(v) and v > 0, "must be a number > 0"),
)
"""(config key, predicate, what is allowed); a key absent from the config is not checked."""


def check_config(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for the first value in ``cfg`` that :data:`CHECKS` rejects."""
    for key, allowed, message in CHECKS:
        value = OmegaConf.select(cfg, key, default=_MISSING)
        if value is _MISSING:
            continue
        if OmegaConf.is_config(value):
            value = OmegaConf.to_container(value, resolve=True)
        if not allowed(value):
            raise ConfigError(key, value, message)
    space = OmegaConf.select(cfg, "benchmark.space")
    if space is not None:
        for name, low, high in zip(space.names, space.low, space.high):
            if not low < high:
                raise ConfigError(
                    "benchmark.space.low",
                    list(space.low),
                    f"must be < benchmark.space.high for every identifier "
                    f"({name}: {low} >= {high})",
                )
    check_task_split(cfg)


def check_task_split(cfg: DictConfig) -> None:
    """A collector that splits the tasks over ``benchmark.collector.workers`` processes needs every
    task count it collects to divide evenly: checked here for the meta-batch and ``eval.n_tasks``,
    so a bad split fails before training rather than at the evaluation after it."""
    workers = OmegaConf.select(cfg, "benchmark.collector.workers", default=None)
    if workers is None:
        return
    if not _positive_int(workers):
        raise ConfigError("benchmark.collector.workers", workers, "must be an integer >= 1")
    for key in ("trainer.meta_batch", "eval.n_tasks"):
        count = OmegaConf.select(cfg, key)
        if count % workers:
            raise ConfigError(
                "benchmark.collector.workers", workers, f"must divide {key} = {count}"
            )


def load_run_config(run_dir: str | Path, key: str) -> DictConfig:
    """The resolved config saved in ``run_dir``; ``key`` names the option that pointed there."""
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise ConfigError(key, str(run_dir), f"is not a run directory (no {CONFIG_FILE})")
    return OmegaConf.load(path)
