"""Run configs: the typed schema of every known config key (its type and allowed range, declared
once), its check, and loading the resolved config a run directory keeps.

The schema is a tree of dataclasses, :class:`TrainSchema` at its root, mirroring
``configs/train.yaml``. A field's annotation is the key's type (``bool``, ``int``, ``float``,
``str``, ``list[...]``, ``X | None``, a nested schema, or ``Any`` / ``dict[str, Any]`` for parts
a benchmark or method fills freely, such as collector arguments); its metadata
(:func:`armeta_rl.fields.key`) is the range and its wording. The YAML files keep the values,
but for a learner's and a risk principle's options: their defaults are the fields' (each
learner's or principle's module's :class:`~armeta_rl.fields.Options`, registered in
:data:`armeta_rl.factory.LEARNERS` and :data:`armeta_rl.factory.PRINCIPLES`), from which
:data:`LearnerSchema`, :data:`RiskSchema` and the composed ``learner:`` and ``risk:`` sections
are derived.
:func:`check_config` checks a composed config against the schema, strictly:
``first_order: off`` is a string, not a boolean, and is refused. Keys present only with some
benchmarks or methods (``benchmark.collector.workers``) are checked when present. See
docs/configuration.md.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf, open_dict

from armeta_rl.devices import DEVICE_FORMS, is_device_name, resolve_device
from armeta_rl.errors import ConfigError
from armeta_rl.factory import LEARNERS, learner_sections, risk_sections
from armeta_rl.fields import (  # noqa: F401 (_conforms: the schema tests check types with it)
    _MISSING,
    _check_node,
    _conforms,
    _optional,
    above,
    at_least,
    defaults,
    each,
    inside,
    key,
    one_of,
)
from armeta_rl.preemption import STOP_SIGNALS

CONFIG_FILE = "config.yaml"
SEED_RANGE = (-(2**63), 2**64 - 1)
"""The seeds ``torch.manual_seed`` accepts."""


def method_name(risk: str, learner: str) -> str:
    """A method's name, which names its run directories: the learner's for expected risk
    minimization (``maml``), else the risk principle's and the learner's (``ar_maml``). Composed
    configs give ``method.name`` as ``${method_name:${method.risk},${method.learner}}``, so
    ``method.learner=anil`` names an ``ar_anil`` run without a method file."""
    return learner if risk == "erm" else f"{risk}_{learner}"


OmegaConf.register_new_resolver("method_name", method_name, replace=True)


def seeds(top: int = SEED_RANGE[1]) -> Any:
    low = SEED_RANGE[0]
    return key(
        f"must be in [-2^63, {'2^64 - 1' if top == SEED_RANGE[1] else '2^64 - 2'}] "
        "(torch's seed range)",
        lambda v: low <= v <= top,
    )


@dataclass
class TrainerSchema:
    iterations: int = at_least(1)
    meta_batch: int = at_least(1)
    log_every: int = at_least(1)
    checkpoint_every: int = at_least(1)
    stop_at: int | None = at_least(1)
    progress: bool = key()
    keep_freed_memory: bool = key(old_runs=True)
    max_loss: float | None = key("must be > 0", lambda v: v > 0, old_runs=None)
    density_every: int = key("must be >= 0 (0: no density frames)", lambda v: v >= 0, old_runs=0)
    frozen_leader: str | None = key(old_runs=None)  # checked by armeta_rl.trainers.players
    stop_signals: list[str] = key(f"every element must be one of {', '.join(STOP_SIGNALS)}",
                                  lambda v: all(name in STOP_SIGNALS for name in v),
                                  old_runs=["SIGTERM", "SIGUSR1"])


@dataclass
class EvalSchema:
    n_tasks: int = at_least(1)
    alphas: list[float] = each(inside(0, 1), nonempty=True)
    seed: int = seeds(SEED_RANGE[1] - 1)  # the adversarial distribution is scored at seed + 1
    support_noise: float = at_least(0)


RiskSchema = dataclasses.make_dataclass(
    "RiskSchema", [(name, options, key()) for name, options in risk_sections().items()]
)
RiskSchema.__doc__ = """``risk:``: one section per risk principle of
:data:`armeta_rl.factory.PRINCIPLES` that has options, its options."""


@dataclass
class MethodSchema:
    name: str = key()
    learner: str = key()  # a name of armeta_rl.factory.LEARNERS: checked by check_config
    risk: str = one_of("erm", "ar", "dr", "tr", "dro")


@dataclass
class LoggerSchema:
    kind: str = one_of("csv", "wandb", "none")
    project: str | None = key()


@dataclass
class SpaceSchema:
    names: list[str] = key("needs at least one identifier", lambda v: len(v) > 0)
    low: list[float] = key()
    high: list[float] = key()


@dataclass
class InitialSchema:
    kind: str = one_of("uniform", "normal")
    loc: list[float] | None = key()
    scale: list[float] | None = each(above(0))


@dataclass
class BenchmarkSchema:
    name: str = key()
    space: SpaceSchema = key()
    initial: InitialSchema = key()
    collector: dict[str, Any] = key()  # the collector's arguments: checked by the collector
    eval_collector: dict[str, Any] = key()
    model: dict[str, Any] | None = key()  # the model's choices (head), if any: make_mlp checks


@dataclass
class TrainSchema:
    """The root of the ``armeta-train`` config (``configs/train.yaml``)."""

    seed: int = seeds()
    device: str = key(f"allowed: {DEVICE_FORMS}", is_device_name, old_runs="cpu")
    threads: int = at_least(1)
    resume: str | None = key()
    trainer: TrainerSchema = key()
    eval: EvalSchema = key()
    learner: LearnerSchema = key()
    risk: RiskSchema = key()
    method: MethodSchema = key()
    logger: LoggerSchema = key()
    benchmark: BenchmarkSchema = key()


def schema_keys(schema: type = TrainSchema, prefix: str = "") -> dict[str, dataclasses.Field]:
    """Every key the schema declares (dotted) and its field, leaves and groups alike."""
    keys = {}
    hints = typing.get_type_hints(schema)
    for spec in dataclasses.fields(schema):
        name = f"{prefix}{spec.name}"
        keys[name] = spec
        nested = _optional(hints[spec.name]) or hints[spec.name]
        if dataclasses.is_dataclass(nested):
            keys.update(schema_keys(nested, f"{name}."))
    return keys


REMOVED_KEYS: dict[str, Any] = {
    "benchmark.collector.compile": False,
    "benchmark.eval_collector.compile": False,
}
"""Keys that configs saved by earlier versions may hold, with the value under which a saved run
behaves as today's code runs it (the compiled system-identification env step was removed:
docs/speed-options.md)."""


def without_removed_keys(cfg: DictConfig) -> DictConfig:
    """``cfg`` (a run directory's saved config) without the keys of :data:`REMOVED_KEYS`; a key
    saved at another value than today's behaviour is refused (:class:`ConfigError`)."""
    present = {}
    for name, today in REMOVED_KEYS.items():
        value = OmegaConf.select(cfg, name, default=_MISSING)
        if value is _MISSING:
            continue
        if value != today:
            raise ConfigError(name, value, f"was removed; a saved run needs it at {today!r}")
        present[name] = value
    if not present:
        return cfg
    cfg = cfg.copy()
    with open_dict(cfg):
        for name in present:
            parent, _, leaf = name.rpartition(".")
            OmegaConf.select(cfg, parent).pop(leaf)
    return cfg


def with_old_run_defaults(cfg: DictConfig) -> DictConfig:
    """``cfg`` (a run directory's saved config) with the keys added since it was saved, at the
    values that keep such a run behaving as it did (their ``old_runs``)."""
    added = {}
    for name, spec in schema_keys().items():
        if spec.metadata["old_runs"] is not _MISSING and OmegaConf.select(
            cfg, name, default=_MISSING
        ) is _MISSING:
            added[name] = spec.metadata["old_runs"]
    if not added:
        return cfg
    cfg = cfg.copy()
    with open_dict(cfg):
        for name, value in added.items():
            OmegaConf.update(cfg, name, value, force_add=True)
    return cfg


def check_config(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for the first value in ``cfg`` that the schema rejects (its
    type, then its range), then for the device (present on this machine) and the rules between
    keys (identifier box, task split)."""
    _check_node(TrainSchema, OmegaConf.to_container(cfg, resolve=True), "")
    device = OmegaConf.select(cfg, "device")
    if device is not None:
        resolve_device(device)
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
    check_learner(cfg)


def check_learner(cfg: DictConfig) -> None:
    """``method.learner`` names a registered learner (:data:`armeta_rl.factory.LEARNERS`)."""
    name = OmegaConf.select(cfg, "method.learner")
    if name is not None and name not in LEARNERS:
        raise ConfigError("method.learner", name, f"allowed: {', '.join(LEARNERS)}")


def check_task_split(cfg: DictConfig) -> None:
    """A collector that splits the tasks over ``benchmark.collector.workers`` processes needs every
    task count it collects to divide evenly: checked here for the meta-batch and ``eval.n_tasks``,
    so a bad split fails before training rather than at the evaluation after it."""
    workers = OmegaConf.select(cfg, "benchmark.collector.workers", default=None)
    if workers is None:
        return
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError("benchmark.collector.workers", workers, "must be an integer >= 1")
    for name in ("trainer.meta_batch", "eval.n_tasks"):
        count = OmegaConf.select(cfg, name)
        if count % workers:
            raise ConfigError(
                "benchmark.collector.workers", workers, f"must divide {name} = {count}"
            )


def required_keys(schema: type = TrainSchema, prefix: str = "") -> list[str]:
    """The keys every composed config has (dotted): the schema's fields that are neither
    optional nor added after runs were saved (``old_runs``), but for the ``learner:`` and
    ``risk:`` sections, whose builders default what a section lacks."""
    keys = []
    hints = typing.get_type_hints(schema)
    for spec in dataclasses.fields(schema):
        name, hint = f"{prefix}{spec.name}", hints[spec.name]
        if _optional(hint) is not None or spec.metadata["old_runs"] is not _MISSING or (
                name in ("learner", "risk")):
            continue
        keys.append(name)
        if dataclasses.is_dataclass(hint):
            keys += required_keys(hint, f"{name}.")
    return keys


def load_run_config(run_dir: str | Path, key: str) -> DictConfig:
    """The resolved config saved in ``run_dir`` (with the keys added since, at their ``old_runs``
    values); ``key`` names the option that pointed there. A file that does not parse, or lacks a
    key every run's config has (an empty or truncated file), is refused (:class:`ConfigError`)."""
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise ConfigError(key, str(run_dir), f"is not a run directory (no {CONFIG_FILE})")
    try:
        cfg = OmegaConf.load(path)
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        reason = " ".join(str(error).split())
        raise ConfigError(
            key, str(run_dir), f"its {CONFIG_FILE} cannot be read: {reason}"
        ) from None
    if not isinstance(cfg, DictConfig):
        raise ConfigError(key, str(run_dir), f"its {CONFIG_FILE} is not a mapping of keys")
    cfg = with_old_run_defaults(without_removed_keys(cfg))
    missing = next((name for name in required_keys()
                    if OmegaConf.select(cfg, name, default=_MISSING) is _MISSING), None)
    if missing is not None:
        raise ConfigError(key, str(run_dir), f"its {CONFIG_FILE} is incomplete (no '{missing}'; "
                          "empty or cut short): restore it, or train the run again")
    return cfg


LearnerSchema = dataclasses.make_dataclass(
    "LearnerSchema", [(name, options, key()) for name, options in learner_sections().items()]
)
LearnerSchema.__doc__ = """``learner:``: one section per learner of
:data:`armeta_rl.factory.LEARNERS` and per meta-RL form, its options."""

# configs/train.yaml composes `learner_options`: the `learner:` section, every learner's options at
# their defaults, so a learner's values are declared once, in its options. (A root config, not a
# config group: `learner=x` stays a value, refused by the schema as before.)
ConfigStore.instance().store(
    name="learner_options",
    node={"learner": {name: defaults(options) for name, options in learner_sections().items()}},
)
# ... and `risk_options`, the `risk:` section: every risk principle's options at their defaults.
ConfigStore.instance().store(
    name="risk_options",
    node={"risk": {name: defaults(options) for name, options in risk_sections().items()}},
)
