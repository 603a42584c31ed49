"""Run configs: the typed schema of every known config key (its type and allowed range, declared
once), its check, and loading the resolved config a run directory keeps.

The schema is a tree of dataclasses, :class:`TrainSchema` at its root, mirroring
``configs/train.yaml``. A field's annotation is the key's type (``bool``, ``int``, ``float``,
``str``, ``list[...]``, ``X | None``, a nested schema, or ``Any`` / ``dict[str, Any]`` for parts
a benchmark or method fills freely, such as collector arguments); its :func:`key` metadata is the
range and its wording. The YAML files keep the values, but for a learner's options: their
defaults are the fields' (each learner module's options dataclass, registered in
:data:`armeta_rl.factory.LEARNERS`), from which :data:`LearnerSchema` and the composed
``learner:`` section are derived. :func:`check_config` checks a composed
config against the schema, strictly: ``first_order: off`` is a string, not a boolean, and is
refused. Keys present only with some benchmarks or methods (``benchmark.collector.workers``)
are checked when present. See docs/configuration.md.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Union

import yaml
from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf, open_dict

from armeta_rl.devices import DEVICE_FORMS, is_device_name, resolve_device
from armeta_rl.errors import ConfigError

_MISSING = object()
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


def key(
    allowed: str = "",
    test: Callable[[Any], bool] | None = None,
    old_runs: Any = _MISSING,
    default: Any = None,
) -> Any:
    """A schema field: ``test`` (on a value of the right type) and ``allowed``, the end of the
    error line when it fails (``must be >= 1``, ``allowed: a, b``); ``old_runs`` is the value a
    run directory saved before the key existed gets when it is loaded (only for keys added after
    runs were saved); ``default`` is the key's value in a composed config, for the keys whose
    values are declared here rather than in ``configs/`` (a learner's options, :func:`defaults`)."""
    metadata = {"allowed": allowed, "test": test, "old_runs": old_runs}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=metadata)
    return field(default=default, metadata=metadata)


def at_least(low: float, default: Any = None) -> Any:
    return key(f"must be >= {low:g}", lambda v: v >= low, default=default)


def above(low: float, default: Any = None) -> Any:
    return key(f"must be > {low:g}", lambda v: v > low, default=default)


def inside(low: float, high: float, closed: str = "()", default: Any = None) -> Any:
    """In the interval from ``low`` to ``high``; ``closed`` gives its brackets, e.g. ``"(]"``."""
    lo = (lambda v: v >= low) if closed[0] == "[" else (lambda v: v > low)
    hi = (lambda v: v <= high) if closed[1] == "]" else (lambda v: v < high)
    return key(f"must be in {closed[0]}{low:g}, {high:g}{closed[1]}", lambda v: lo(v) and hi(v),
               default=default)


def one_of(*choices: str, default: Any = None) -> Any:
    return key(f"allowed: {', '.join(choices)}", lambda v: v in choices, default=default)


def each(check: Any, nonempty: bool = False, default: Any = None) -> Any:
    """Every element of a list passes ``check`` (a field made by :func:`at_least` and the like);
    with ``nonempty`` the list must have one at least."""
    words, test = check.metadata["allowed"].removeprefix("must be "), check.metadata["test"]
    allowed = f"must be a non-empty list, every element {words}" if nonempty else (
        f"every element must be {words}")
    return key(allowed, lambda v: (len(v) > 0 or not nonempty) and all(test(a) for a in v),
               default=default)


def defaults(options: type) -> dict[str, Any]:
    """The default value of every key of an options dataclass (a learner's ``learner.<name>``
    section), as a composed config holds them."""
    return dataclasses.asdict(options())


@dataclass(frozen=True)
class Options:
    """A learner's options: the keys of its config section ``section`` (``"learner.maml"``), one
    field each, made with this module's helpers (type, range and default value, declared once).
    The learner's constructor takes them
    (``MAMLLeader(model, collector, MamlOptions(inner_lr=0.05))``) and its builder makes them
    from the section (``MamlOptions(**section(cfg, "learner.maml"))``). They are checked when
    made, so a bad value from Python is refused with the line the CLI prints
    (``config key 'learner.maml.inner_lr' = 0: must be > 0``)."""

    section: ClassVar[str]

    def __post_init__(self) -> None:
        values = {spec.name: getattr(self, spec.name) for spec in dataclasses.fields(self)}
        _check_node(type(self), _plain(values), f"{self.section}.")


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
    max_loss: float | None = key("must be > 0", lambda v: v > 0, old_runs=None)
    density_every: int = key("must be >= 0 (0: no density frames)", lambda v: v >= 0, old_runs=0)
    frozen_leader: str | None = key(old_runs=None)  # checked by armeta_rl.trainers.players


@dataclass
class EvalSchema:
    n_tasks: int = at_least(1)
    alphas: list[float] = each(inside(0, 1), nonempty=True)
    seed: int = seeds(SEED_RANGE[1] - 1)  # the adversarial distribution is scored at seed + 1
    support_noise: float = at_least(0)


@dataclass
class ArSchema:
    flow: str = one_of("spline", "planar")
    flow_kwargs: dict[str, Any] = key()  # the flow's own arguments: checked by the flow
    lam: float = key("must be >= 0 (λ ≥ 0)", lambda v: v >= 0)
    update_every: int = at_least(1)
    lr: float = above(0)
    grad_clip: float | None = above(0)
    baseline: str = one_of("mean", "leave_one_out")
    initial_samples: int = at_least(1)
    compile: Any = key()


@dataclass
class DrSchema:
    alpha: float = inside(0, 1)
    oversample: bool = key()


@dataclass
class GroupsSchema:
    groups_per_axis: int = at_least(1)
    step_size: float = above(0)


@dataclass
class RiskSchema:
    ar: ArSchema = key()
    dr: DrSchema = key()
    tr: GroupsSchema = key()
    dro: GroupsSchema = key()


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
    model: dict[str, Any] = key()  # the model's choices (head): checked by make_mlp


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


def _type_words(hint: Any) -> str:
    """What a value of type ``hint`` is, in words: ``an integer``, ``a list of numbers``, ..."""
    if _optional(hint) is not None:
        return f"{_type_words(_optional(hint))} or null"
    origin = typing.get_origin(hint)
    if origin is list:
        inner = _type_words(typing.get_args(hint)[0]).split(" ", 1)[1]
        return f"a list of {inner}s"
    if origin is dict or dataclasses.is_dataclass(hint):
        return "a group of keys"
    return {bool: "a boolean (true or false)", int: "an integer", float: "a finite number",
            str: "a string"}[hint]


def _optional(hint: Any) -> Any:
    """``X`` for ``X | None``, else ``None``."""
    if typing.get_origin(hint) in (Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return args[0]
    return None


def _conforms(value: Any, hint: Any) -> bool:
    """Whether ``value`` (plain Python) has type ``hint``, strictly (no string is a boolean)."""
    if hint is Any:
        return True
    if _optional(hint) is not None:
        return value is None or _conforms(value, _optional(hint))
    origin = typing.get_origin(hint)
    if origin is list:
        return isinstance(value, list) and all(
            _conforms(v, typing.get_args(hint)[0]) for v in value
        )
    if origin is dict or dataclasses.is_dataclass(hint):
        return isinstance(value, dict)
    if hint is float:
        return (isinstance(value, (int, float)) and not isinstance(value, bool)
                and math.isfinite(value))
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, hint)


def _check_node(schema: type, node: dict, prefix: str) -> None:
    hints = typing.get_type_hints(schema)
    for spec in dataclasses.fields(schema):
        if spec.name not in node:
            continue
        name, value, hint = f"{prefix}{spec.name}", node[spec.name], hints[spec.name]
        if not _conforms(value, hint):
            choices = spec.metadata["allowed"] if spec.metadata["allowed"].startswith(
                "allowed:") else ""
            raise ConfigError(name, value, f"must be {_type_words(hint)}" + (
                f"; {choices}" if choices else ""))
        if value is None:
            continue
        nested = _optional(hint) or hint
        if dataclasses.is_dataclass(nested):
            _check_node(nested, value, f"{name}.")
        test = spec.metadata["test"]
        if test is not None and not test(value):
            raise ConfigError(name, value, spec.metadata["allowed"])


def check_keys(prefix: str, **values: Any) -> None:
    """Check constructor arguments that are the config keys ``<prefix>.<name>`` (e.g.
    ``check_keys("risk.dr", alpha=alpha)``) against their schema fields: an object built from
    Python rather than from a config refuses a bad value with the same line as the CLI."""
    schema = TrainSchema
    for name in prefix.split("."):
        hint = typing.get_type_hints(schema)[name]
        schema = _optional(hint) or hint
    _check_node(schema, _plain(values), f"{prefix}.")


def _plain(values: dict[str, Any]) -> dict[str, Any]:
    """``values`` as a config holds them: a tuple (``hidden=(64, 64)``) is a list."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in values.items()}


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


def section(cfg: DictConfig, key: str) -> dict[str, Any]:
    """The keys under ``key`` of a composed config as a plain, resolved dict (``{}`` when absent):
    what a builder hands on as arguments (``section(cfg, "learner.anil")``)."""
    node = OmegaConf.select(cfg, key)
    return {} if node is None else OmegaConf.to_container(node, resolve=True)


def check_task_split(cfg: DictConfig) -> None:
    """A collector that splits the tasks over ``benchmark.collector.workers`` processes needs every
    task count it collects to divide evenly: checked here for the meta-batch and ``eval.n_tasks``,
    so a bad split fails before training rather than at the evaluation after it."""
    workers = OmegaConf.select(cfg, "benchmark.collector.workers", default=None)
    if workers is None:
        return
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError("benchmark.collector.workers", workers, "must be an integer >= 1")
    for key in ("trainer.meta_batch", "eval.n_tasks"):
        count = OmegaConf.select(cfg, key)
        if count % workers:
            raise ConfigError(
                "benchmark.collector.workers", workers, f"must divide {key} = {count}"
            )


def load_run_config(run_dir: str | Path, key: str) -> DictConfig:
    """The resolved config saved in ``run_dir`` (with the keys added since, at their ``old_runs``
    values); ``key`` names the option that pointed there."""
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
    return with_old_run_defaults(without_removed_keys(cfg))


# The registry's learner modules declare their options with this module's helpers, so it is
# imported once they are defined.
from armeta_rl.factory import LEARNERS, learner_sections  # noqa: E402

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
