"""The ``armeta-train`` config: its root sections as dataclasses (each key's default and range),
their check, and loading the config a run directory keeps.

:class:`TrainConfig` is the structured config ``configs/train.yaml`` composes first; the
learners' and risk principles' sections (``learner.maml``, ``risk.ar``) are their modules' own
dataclasses, registered in Hydra's ConfigStore by :func:`armeta_rl.fields.register` and listed in
the defaults of ``configs/train.yaml``. This module imports none of them. Hydra checks every
value's type and refuses unknown keys as it composes; :func:`validate` makes the dataclasses,
which checks every range and the rules between keys and resolves ``device``. The CLI calls it
once per run (a resumed run: on its saved config merged with the command line's changes,
:func:`load_run`), and everything below the CLI takes the :class:`TrainConfig` it returns. See
docs/configuration.md.
"""

from __future__ import annotations

import copy
import functools
import inspect
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from armeta_rl.errors import ConfigError
from armeta_rl.fields import Section, above, at_least, config_error, each, inside, key, one_of
from armeta_rl.preemption import STOP_SIGNALS
from armeta_rl.resources import (
    FLOAT32_BYTES,
    FLOAT64_BYTES,
    hidden_units,
    machine_memory,
    sample_bytes,
    sample_counts,
    samples_per_task,
    size_words,
    spline_layer_parameters,
    task_batch_bytes,
    usable_cpus,
)
from armeta_rl.run_files import FileRefused, plain_yaml, read_text

if TYPE_CHECKING:
    import torch

CONFIG_FILE = "config.yaml"
CONFIG_BYTES = 2**20
"""The most a run's ``config.yaml`` is read (a few KiB in practice)."""
SEED_RANGE = (-(2**63), 2**64 - 1)
"""The seeds ``torch.manual_seed`` accepts."""


def method_name(risk: str, learner: str) -> str:
    """A method's name, which names its run directories: the learner's for expected risk
    minimization (``maml``), else the risk principle's and the learner's (``ar_maml``). Composed
    configs give ``method.name`` as ``${method_name:${method.risk},${method.learner}}``, so
    ``method.learner=anil`` names an ``ar_anil`` run without a method file."""
    return learner if risk == "erm" else f"{risk}_{learner}"


OmegaConf.register_new_resolver("method_name", method_name, replace=True)


def seeds(top: int = SEED_RANGE[1], default: int = 0) -> Any:
    low = SEED_RANGE[0]
    words = "2^64 - 1" if top == SEED_RANGE[1] else "2^64 - 2"
    return key(f"must be in [-2^63, {words}] (torch's seed range)", lambda v: low <= v <= top,
               default)


@dataclass
class TrainerConfig(Section):
    """``trainer``: the game loop's length, logging, checkpoints and guards."""

    section = "trainer"

    iterations: int = at_least(1, 4000)  # the default run (ar_maml, sinusoid) < 5 min on 2 cores
    meta_batch: int = at_least(1, 25)
    log_every: int = at_least(1, 50)
    checkpoint_every: int = at_least(1, 500)
    stop_at: int | None = at_least(1)  # stop (with a checkpoint) after this iteration; resume later
    # divergence guard: a task loss beyond ±max_loss stops the run (exit 1); null: only
    # non-finite losses stop it
    max_loss: float | None = key("must be > 0", lambda v: v > 0, 1.0e6)
    # draw p_φ every N iterations (AR methods) into <run>/density/iter_N.png (and wandb),
    # density.gif at the end; 0: off
    density_every: int = key("must be >= 0 (0: no density frames)", lambda v: v >= 0,
                             "${trainer.checkpoint_every}")
    progress: bool = key(default=True)
    # glibc keeps freed blocks for reuse instead of returning them to the kernel (faster, same
    # values; docs/speed-options.md)
    keep_freed_memory: bool = key(default=True)
    # a finished run directory (same benchmark and learner): its learner is loaded and never
    # trained; only the adversary (AR methods) learns against it (checked by
    # armeta_rl.trainers.players; docs/protocol.md)
    frozen_leader: str | None = key()
    # meta-RL: the follower's loss of a task is the mean of this many fresh rollouts at θ_{t+1}
    # (1: the paper's single rollout; docs/meta-rl.md)
    follower_rollouts: int = at_least(1, 1)
    # which losses a follower of the game (AR, TR, DRO) reads: "next", L(τ; θ_{t+1}) after the
    # leader's step (paper Algorithm 1; a fresh collection in meta-RL), or "step", the step's
    # own L(τ; θ_t), which cost nothing more (as MPTS and PDTS read theirs; docs/meta-rl.md)
    follower_at: str = one_of("next", "step", default="next")
    # on these signals (and SIGINT) a run finishes its iteration, writes a checkpoint and exits
    # 75 (SIGINT: 130) for resume= to continue (armeta_rl/preemption.py; docs/configuration.md)
    stop_signals: list[str] = key(f"every element must be one of {', '.join(STOP_SIGNALS)}",
                                  lambda v: all(name in STOP_SIGNALS for name in v),
                                  ["SIGTERM", "SIGUSR1"])

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.follower_rollouts > 1 and self.follower_at == "step":
            self.refuse("follower_rollouts", "must be 1 with trainer.follower_at=step: the "
                        "follower reads the step's own losses, not fresh rollouts")


@dataclass
class EvalConfig(Section):
    """``eval``: the evaluation after training (every method sees the same tasks)."""

    section = "eval"

    n_tasks: int = at_least(1, 500)
    alphas: list[float] = each(inside(0, 1), nonempty=True, default=[0.5, 0.7, 0.9])
    seed: int = seeds(SEED_RANGE[1] - 1, 1234)  # the adversarial distribution is scored at seed+1
    # > 0 also reports scores with N(0, σ²) noise on the support labels (regression and sys-id,
    # in the labels' units; RL has no labels)
    support_noise: float = at_least(0, 0.0)
    # R: every task is scored on R independent rollouts (adaptation from fresh data, then the
    # loss), averaged; the RL benchmarks set theirs from the noise-against-R curve
    # (docs/meta-rl.md)
    rollouts: int = at_least(1, 1)
    # k: a meta-RL learner is also scored after 0, 1, ..., k inner steps (the report's
    # adaptation_curve); null: the number it trains with and two more
    adaptation_steps: int | None = at_least(1, None)


@dataclass
class MethodConfig(Section):
    """``method``: risk principle × learner (``configs/method/``, or ``method.learner=anil
    method.risk=dr``, a run named ``dr_anil``). The names are checked against the registries
    (:func:`armeta_rl.factory.check_method`)."""

    section = "method"

    learner: str = key(default="maml")
    risk: str = key(default="ar")
    name: str = key(default="${method_name:${method.risk},${method.learner}}")


@dataclass
class LoggerConfig(Section):
    section = "logger"

    kind: str = one_of("csv", "wandb", "tensorboard", "mlflow", "none", default="csv")
    project: str | None = key()
    tracking_uri: str | None = key()  # mlflow's store (default: a SQLite file in the run)


@dataclass
class SpaceConfig(Section):
    """``benchmark.space``: the identifier box."""

    section = "benchmark.space"

    names: list[str] = key("needs at least one identifier", lambda v: len(v) > 0, MISSING)
    low: list[float] = key(default=MISSING)
    high: list[float] = key(default=MISSING)

    def __post_init__(self) -> None:
        super().__post_init__()
        if MISSING in (self.names, self.low, self.high):
            return
        for name, low, high in zip(self.names, self.low, self.high):
            if not low < high:
                self.refuse("low", f"must be < benchmark.space.high for every identifier "
                                   f"({name}: {low} >= {high})")


@dataclass
class InitialConfig(Section):
    """``benchmark.initial``: p0."""

    section = "benchmark.initial"

    kind: str = one_of("uniform", "normal", default="uniform")
    loc: list[float] | None = key()
    scale: list[float] | None = each(above(0))


@dataclass
class BenchmarkConfig(Section):
    """``benchmark``: set by ``configs/benchmark/``."""

    section = "benchmark"

    name: str = key(default="")
    space: SpaceConfig = field(default_factory=SpaceConfig)
    initial: InitialConfig = field(default_factory=InitialConfig)
    # the collectors' Hydra nodes (_target_ and arguments), checked by the collectors
    collector: dict[str, Any] = key(default={})
    eval_collector: dict[str, Any] = key(default={})
    model: dict[str, Any] = key(default={})  # the model's choices (head): checked by make_mlp
    # the shifts no adversary chose: configs/shift_suites/<name>.yaml, checked there
    # (armeta_rl.tasks.shifts); null: the benchmark has no suite
    shift_suite: str | None = key()


@dataclass
class TrainConfig(Section):
    """The root of the ``armeta-train`` config."""

    section = ""

    seed: int = seeds()
    # cpu, cuda or cuda:N: where leaders, task distributions, torch-native envs and evaluation
    # compute (MuJoCo steps on the CPU; docs/scale.md); checked against this machine
    device: str = key(default="cpu")
    # torch intra-op threads; batched small ops are fastest on one; at most the CPUs this process
    # may run on (more only slow it down, and far more crash torch's thread pool)
    threads: int = at_least(1, 1)
    resume: str | None = key()  # a run directory to continue from its latest checkpoint
    # take a checkpoint that records no run (written before checkpoints recorded theirs) as
    # this run's, on resume= and of trainer.frozen_leader; not kept by a resume
    # (docs/configuration.md, "The trust model")
    adopt: bool = key(default=False)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    method: MethodConfig = field(default_factory=MethodConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    benchmark: BenchmarkConfig = field(default_factory=BenchmarkConfig)
    # learner.<name>, risk.<name>: each a registered section (armeta_rl.fields.register)
    learner: dict[str, Any] = key(default={})
    risk: dict[str, Any] = key(default={})

    def __post_init__(self) -> None:
        from armeta_rl.devices import resolve_device  # torch: not for reading the keys (--help)

        super().__post_init__()
        self._device = resolve_device(self.device)
        self.check_task_split()
        self.check_machine()

    @property
    def torch_device(self) -> torch.device:
        """``device`` as the ``torch.device`` it was resolved to when this config was checked
        (the one resolution of a run: the builders take this object)."""
        return self._device

    def values(self) -> dict[str, Any]:
        """Every key's value as plain, resolved YAML types: what ``config.yaml`` saves, what
        :func:`~armeta_rl.trainers.checkpoint.run_identity` digests and wandb records."""
        return OmegaConf.to_container(OmegaConf.structured(self), resolve=True)

    def check_machine(self) -> None:
        """``threads`` within this process's CPUs, and the sizes within the device's memory:
        :mod:`armeta_rl.resources`' lower bound of what each needs, before any allocation."""
        cpus = usable_cpus()
        if self.threads > cpus:
            self.refuse("threads", f"must be <= {cpus}, the CPUs this process may run on")
        memory = machine_memory(self.device)
        sections = {f"learner.{name}": options for name, options in self.learner.items()
                    if name == self.method.learner or name.startswith(f"{self.method.learner}_")}
        units = min((hidden_units(options) for options in sections.values()), default=1)
        for name, tasks, collector, section in (
                ("trainer.meta_batch", self.trainer.meta_batch, self.benchmark.collector,
                 "benchmark.collector"),
                ("eval.n_tasks", self.eval.n_tasks, self.benchmark.eval_collector,
                 "benchmark.eval_collector")):
            each = task_batch_bytes(1, collector, units, section)
            samples = samples_per_task(collector, section)
            if each > memory:  # one task is too large: the collector's count says so
                counts = sample_counts(collector, section)
                largest = max(counts, key=counts.get)
                raise ConfigError(f"{section}.{largest}", counts[largest], (
                    f"a task's {samples} samples x {units} hidden units x 4 bytes need at "
                    f"least {size_words(each)} of this device's {size_words(memory)}"))
            if tasks * each > memory:
                raise ConfigError(name, tasks, (
                    f"needs at least {size_words(tasks * each)} ({samples} samples x {units} "
                    f"hidden units x 4 bytes per task) of this device's {size_words(memory)}: "
                    f"allowed: at most {memory // each}"))
        for section, options in sections.items():
            self.check_learner_sizes(section, options, memory)
        adversary = self.risk.get(self.method.risk) if self.method.risk == "ar" else None
        samples = getattr(adversary, "initial_samples", None)
        if samples is not None and self.benchmark.space.names != MISSING:
            dim = len(self.benchmark.space.names)
            if sample_bytes(samples, dim) > memory:
                raise ConfigError(f"risk.{self.method.risk}.initial_samples", samples, (
                    f"needs at least {size_words(sample_bytes(samples, dim))} of this device's "
                    f"{size_words(memory)}: allowed: at most {memory // sample_bytes(1, dim)}"))
            self.check_flow_sizes(adversary, samples, dim, memory)

    def check_flow_sizes(self, adversary: Any, samples: int, dim: int, memory: int) -> None:
        """The flow adversary's sizes within the device's memory: every layer keeps its samples
        (the p0 sample and the meta-batch, float64) for the gradient, and a spline layer's
        parameters (float64) take four times their size with their gradients and Adam's two
        moments (:func:`~armeta_rl.resources.spline_layer_parameters`); a size that is not an
        integer is left to the flow to refuse."""
        from armeta_rl.adversary.flows import SplineBoxFlow

        kwargs = dict(adversary.flow_kwargs)
        sizes = {name: kwargs.get(name, argument.default) for name, argument
                 in inspect.signature(SplineBoxFlow).parameters.items()
                 if name in ("layers", "bins", "hidden", "blocks")}
        if any(v is not None and (isinstance(v, bool) or not isinstance(v, int))
               for v in sizes.values()):
            return
        parameters = 0
        if adversary.flow == "spline":
            parameters = 4 * FLOAT64_BYTES * spline_layer_parameters(
                dim, sizes["bins"], sizes["hidden"], sizes["blocks"])
            if parameters > memory:
                given = {k: v for k, v in kwargs.items() if k in ("bins", "hidden", "blocks")}
                raise ConfigError("risk.ar.flow_kwargs", given or kwargs, (
                    f"one spline layer's parameters need at least {size_words(parameters)} of "
                    f"this device's {size_words(memory)}"))
        layers = sizes["layers"]
        each = sample_bytes(samples + self.trainer.meta_batch, dim) + parameters
        if layers is not None and layers * each > memory:
            raise ConfigError("risk.ar.flow_kwargs.layers", layers, (
                f"needs at least {size_words(layers * each)} (every layer keeps its "
                f"{samples + self.trainer.meta_batch} samples for the gradient"
                + (", and its parameters with their gradients and Adam's moments"
                   if parameters else "")
                + f") of this device's {size_words(memory)}: allowed: at most "
                f"{memory // each}"))

    def check_learner_sizes(self, section: str, options: Any, memory: int) -> None:
        """A learner section's sizes within the device's memory: its hidden widths' weights
        (float32, between consecutive hidden layers) and its inner steps, each of which keeps a
        forward pass's activations over the meta-batch for the meta-gradient."""
        fields = options if isinstance(options, Mapping) else vars(options)
        name = "hidden" if "hidden" in fields else "hidden_sizes"
        value = fields.get(name) or []
        widths = [int(w) for w in ([value] if isinstance(value, int) else value)]
        weights = FLOAT32_BYTES * sum(a * b for a, b in zip(widths, widths[1:]))
        if weights > memory:
            raise ConfigError(f"{section}.{name}", widths, (
                f"its weights need at least {size_words(weights)} of this device's "
                f"{size_words(memory)}"))
        steps = fields.get("inner_steps")
        if steps is not None:
            each = task_batch_bytes(self.trainer.meta_batch, self.benchmark.collector,
                                    hidden_units(options))
            if steps * each > memory:
                raise ConfigError(f"{section}.inner_steps", steps, (
                    f"needs at least {size_words(steps * each)} (every step keeps a forward "
                    f"pass over the meta-batch) of this device's {size_words(memory)}: "
                    f"allowed: at most {memory // each}"))

    def check_task_split(self) -> None:
        """A collector that splits the tasks over ``benchmark.collector.workers`` processes needs
        every task count it collects to divide evenly: checked for the meta-batch and
        ``eval.n_tasks``, so a bad split fails before training rather than at the evaluation."""
        workers = self.benchmark.collector.get("workers")
        if workers is None:
            return
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ConfigError("benchmark.collector.workers", workers, "must be an integer >= 1")
        for name, count in (("trainer.meta_batch", self.trainer.meta_batch),
                            ("eval.n_tasks", self.eval.n_tasks)):
            if count % workers:
                raise ConfigError("benchmark.collector.workers", workers,
                                  f"must divide {name} = {count}")


ConfigStore.instance().store(group="schema", name="train", node=TrainConfig, package="_global_")


def validate(cfg: DictConfig) -> TrainConfig:
    """``cfg`` (a composed or loaded config) as its dataclasses: every range and the rules
    between keys checked (:class:`~armeta_rl.errors.ConfigError` for the first bad value)."""
    try:
        return OmegaConf.to_object(cfg)
    except OmegaConfBaseException as error:
        raise config_error(error) from None


def schema() -> DictConfig:
    """The typed config every run's is merged into: :class:`TrainConfig` with every registered
    ``learner.<name>`` and ``risk.<name>`` section at its defaults."""
    store = ConfigStore.instance()
    cfg = OmegaConf.structured(TrainConfig)
    for group in ("learner", "risk"):
        for entry in store.list(f"schema/{group}"):
            name = entry.removesuffix(".yaml")
            cfg[group][name] = store.load(f"schema/{group}/{entry}").node
    return cfg


def load_run(run_dir: str | Path, key: str, changes: Mapping[str, Any] | None = None
             ) -> TrainConfig:
    """The config saved in ``run_dir`` (:func:`load_run_config`) with ``changes`` merged in,
    checked (:func:`validate`); ``key`` names the option that pointed there."""
    saved = load_run_config(run_dir, key)
    try:
        merged = OmegaConf.merge(saved, changes or {})
    except OmegaConfBaseException as error:
        raise config_error(error) from None
    return validate(merged)


def run_values(run_dir: str | Path, key: str) -> dict[str, Any]:
    """The values of the config saved in ``run_dir`` (:func:`load_run_config`), resolved, as
    plain YAML types, not checked: what another run compares its own with."""
    return OmegaConf.to_container(load_run_config(run_dir, key), resolve=True)


def load_run_config(run_dir: str | Path, key: str) -> DictConfig:
    """The resolved config saved in ``run_dir``, typed (:func:`schema`), not checked (a resume
    merges the command line's changes first, :func:`load_run`); ``key`` names the option that
    pointed there. A file that does not parse, or lacks a section every run's config has
    (:data:`SAVED_SECTIONS`: an empty or truncated file), is refused: merged into the schema it
    would silently take defaults."""
    path = Path(run_dir) / CONFIG_FILE
    try:
        text = read_text(path, CONFIG_BYTES, run_dir)
    except FileNotFoundError:
        raise ConfigError(key, str(run_dir), f"is not a run directory (no {CONFIG_FILE})"
                          ) from None
    except FileRefused as error:
        raise ConfigError(key, str(run_dir), f"its {CONFIG_FILE} {error.reason}") from None
    except OSError as error:  # e.g. a name the file system cannot hold
        raise ConfigError(key, str(run_dir), f"its {CONFIG_FILE} cannot be read "
                          f"({error.strerror or error})") from None
    return read_run_config(text, key, str(run_dir))


def read_run_config(text: str, key: str, where: str) -> DictConfig:
    """A run's saved ``config.yaml`` ``text`` as a resume reads it (:func:`load_run_config`):
    merged into this version's schema, so keys added since take their defaults; ``key`` and
    ``where`` name it in a refusal: a text that does not parse, is not a mapping, lacks a section
    every run's config has (:data:`SAVED_SECTIONS`: an empty or truncated file) or does not fit
    the schema, or uses YAML anchors or aliases (:func:`~armeta_rl.run_files.plain_yaml`).
    A copy of the reading remembered by text and the registered sections: a sweep's evaluations
    read each run's config several times, and merging it into the schema is most of a small
    evaluation's time."""
    store = ConfigStore.instance()
    registered = tuple(tuple(store.list(f"schema/{group}")) for group in ("learner", "risk"))
    merged = _merged_into_schema(text, registered)
    if isinstance(merged, str):
        raise ConfigError(key, where, merged)
    return copy.deepcopy(merged)


@functools.lru_cache(maxsize=256)
def _merged_into_schema(text: str, registered: tuple[tuple[str, ...], ...]) -> DictConfig | str:
    """``text`` merged into :func:`schema` (whose sections are ``registered``), or why it
    cannot be (:func:`read_run_config`'s refusals, without its key and place)."""
    try:
        saved = OmegaConf.create(plain_yaml(text, CONFIG_FILE))
    except FileRefused as error:
        return f"its {CONFIG_FILE} {error.reason}"
    except yaml.YAMLError as error:
        return f"its {CONFIG_FILE} cannot be read: {' '.join(str(error).split())}"
    if not isinstance(saved, DictConfig):
        return f"its {CONFIG_FILE} is not a mapping of keys"
    missing = next((name for name in saved_sections(saved)
                    if OmegaConf.select(saved, name, default=_ABSENT) is _ABSENT), None)
    if missing is not None:
        return (f"its {CONFIG_FILE} is incomplete (no '{missing}'; empty or cut short): "
                "restore it, or train the run again")
    try:
        return OmegaConf.merge(schema(), saved)
    except OmegaConfBaseException as error:
        return f"its {CONFIG_FILE} does not fit this version: {config_error(error)}"


_ABSENT = object()
SAVED_SECTIONS = ("seed", "trainer", "trainer.iterations", "eval", "eval.n_tasks", "method",
                  "method.learner", "method.risk", "logger", "benchmark", "benchmark.name",
                  "benchmark.space", "benchmark.initial", "benchmark.collector",
                  "benchmark.eval_collector", "learner", "risk")
"""The keys every saved run config holds."""


def value_at(values: Mapping[str, Any], key: str) -> Any:
    """The value at dotted ``key`` (``trainer.meta_batch``) in nested resolved ``values``
    (:meth:`TrainConfig.values`, or a saved config loaded as plain YAML); ``None`` where they
    have none.

    Examples:
        >>> from armeta_rl.config import value_at
        >>> value_at({"trainer": {"meta_batch": 20}}, "trainer.meta_batch")
        20
        >>> value_at({"trainer": {"meta_batch": 20}}, "risk.ar.lr") is None
        True
    """
    node: Any = values
    for part in key.split("."):
        node = node.get(part) if isinstance(node, Mapping) else None
    return node


def saved_sections(saved: DictConfig) -> list[str]:
    """The keys a run's saved config must hold: :data:`SAVED_SECTIONS` and the sections of its
    own learner and risk principle (``learner.maml``, ``risk.ar``; those registered, the file's
    last ones: a truncated file loses them, and merged into the schema they would take their
    defaults)."""
    store = ConfigStore.instance()
    own = []
    for group in ("learner", "risk"):
        name = OmegaConf.select(saved, f"method.{group}", default=None)
        if isinstance(name, str) and f"{name}.yaml" in store.list(f"schema/{group}"):
            own.append(f"{group}.{name}")
    return [*SAVED_SECTIONS, *own]
