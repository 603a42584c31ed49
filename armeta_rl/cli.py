"""Console entry points ``armeta-train`` and ``armeta-eval`` (Hydra).

Bad input ends with one line naming the config key, the value and what is allowed (and the
likely key, for a misspelt one), and exit code 2. Every run enters through one door,
:func:`make_job`, which turns a command line, a ``-m`` sweep job's composed config or a resume
directory into a :class:`~armeta_rl.job.Job`: its config composed (Hydra checks the types and
refuses unknown keys) and validated once (:func:`armeta_rl.config.validate`: the ranges, the
rules between keys, the device resolved), or a resumed run's saved config read once and merged
with the command line's changes. The config of every job on the command line is checked before
Hydra starts, and a single run's directory is checked and locked then too, so a refused command
writes nothing. What runs below the CLI takes the job, never a composed config. A run stopped by
a diverged loss or a failed write ends with one line and exit code 1 (:func:`failure`: the one
table of exit codes). See docs/configuration.md.
"""

from __future__ import annotations

import difflib
import errno
import json
import sys
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from armeta_rl.config_files import config_files, group_choices
from armeta_rl.errors import (
    CollectionFailed,
    ConfigError,
    JobFailed,
    RunDirectoryError,
    RunStopped,
    TrainingDiverged,
)
from armeta_rl.preemption import EXIT_INTERRUPTED

if TYPE_CHECKING:
    from armeta_rl.config import TrainConfig
    from armeta_rl.job import Job

GROUPS = ("benchmark", "method", "logger")
"""The config groups a command line chooses from (``benchmark=point_nav``)."""
_ABSENT = object()
_NO_RUN_FLAGS = ("--cfg", "-c", "--help", "-h", "--hydra-help", "--info", "-i",
                 "--shell-completion", "-sc", "--resolve")
_UNCHECKED_FLAGS = ("--help", "-h", "--hydra-help", "--shell-completion", "-sc")
"""Flags whose command composes nothing to check (its words are not overrides)."""


def config_dir() -> Path:
    """The Hydra config directory, ready to compose from: importing :mod:`armeta_rl.factory`
    registers every learner's and risk principle's options and :mod:`armeta_rl.config`'s root
    schema in Hydra's ConfigStore. That import loads the learners (torch), so it is made here,
    where configs are composed, and not by ``import armeta_rl`` or by importing this module."""
    import armeta_rl.factory  # noqa: F401

    return config_files()


class Refused(ValueError):
    """A command refused with one line (``message``) and an exit code."""

    def __init__(self, message: str, code: int = 2) -> None:
        super().__init__(message)
        self.code = code


def _has_key(cfg: DictConfig, key: str) -> bool:
    """Whether dotted ``key`` is in ``cfg`` (also when its value is the mandatory ``???``)."""
    from omegaconf.errors import MissingMandatoryValue

    try:
        return OmegaConf.select(cfg, key, default=_ABSENT, throw_on_missing=True) is not _ABSENT
    except MissingMandatoryValue:
        return True


def _deepest_existing(cfg: DictConfig, key: str) -> tuple[str, object]:
    """The longest prefix of dotted ``key`` that ``cfg`` has, and its node (the root: ``""``)."""
    parts = key.split(".")
    for end in range(len(parts) - 1, 0, -1):
        prefix = ".".join(parts[:end])
        if _has_key(cfg, prefix):
            return prefix, OmegaConf.select(cfg, prefix)
    return "", cfg


def _unknown_key_message(cfg: DictConfig, key: str, value: str, choices: list[str]) -> str:
    """One line for an override of a key ``cfg`` (composed with the group ``choices``) lacks:
    what exists there, the likely typo, and how to add a new key on purpose."""
    parent, node = _deepest_existing(cfg, key)
    where = f"'{parent}'" if parent else "the top level"
    message = f"config key '{key}' = {value}: no such key"
    if choices:
        message += f" with {' '.join(choices)}"
    if not isinstance(node, DictConfig):
        return f"{message} ({where} is a value, not a group of keys)"
    names = sorted(str(name) for name in node)
    if names:
        message += f"; {where} has: {', '.join(names)}"
        missing = key[len(parent) + 1 :] if parent else key
        close = difflib.get_close_matches(missing.split(".")[0], names, n=1)
        if close:
            message += f" (did you mean '{parent + '.' if parent else ''}{close[0]}'?)"
    else:
        message += f"; {where} has no keys yet"
    return message + f"; to add a new key write +{key}={value}"


def _parse(arg: str) -> Any:
    """The Hydra override ``arg`` parses to (:class:`Refused` if it cannot be read)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        (override,) = OverridesParser.create().parse_overrides([arg])
    except HydraException as error:
        raise Refused(f"cannot read the override {arg!r}: {str(error).splitlines()[0]}") from None
    return override


def _is_hydra_key(key: str) -> bool:
    return key.split(".")[0].split("/")[0] == "hydra"


def job_overrides(args: Sequence[str], groups: tuple[str, ...] = GROUPS) -> list[list[str]]:
    """The config overrides (not ``hydra.*``) of every job the command line starts: one list for
    each combination of the values of ``-m`` sweeps such as ``trainer.iterations=5,0``. An
    unknown choice of a group in ``groups`` (``benchmark=``, also inside a sweep) is refused."""
    import itertools

    per_arg = []
    for arg in args:
        if arg.startswith("-") or "=" not in arg:
            continue
        override = _parse(arg)
        key = override.key_or_group
        if _is_hydra_key(key):
            continue
        values = ([str(v) for v in override.sweep_string_iterator()]
                  if override.is_sweep_override() else [arg.split("=", 1)[1]])
        if key in groups:
            allowed = group_choices(key)
            for choice in values:
                if choice not in allowed:
                    raise Refused(f"config key '{key}' = {choice!r}: allowed: "
                                   f"{', '.join(allowed)}")
        name = arg.split("=", 1)[0]
        per_arg.append([f"{name}={value}" for value in values] if len(values) > 1 else [arg])
    return [list(job) for job in itertools.product(*per_arg)]


def _node(cfg: DictConfig, key: str) -> Any:
    parent, _, leaf = key.rpartition(".")
    container = OmegaConf.select(cfg, parent) if parent else cfg
    return container._get_node(leaf) if isinstance(container, DictConfig) else None


def compose_job(job: list[str], config_name: str = "train") -> DictConfig:
    """Compose ``config_name`` with the overrides ``job`` (inside Hydra's initialized config
    dir). A key the config lacks or a value of the wrong type is refused as one line
    (:class:`Refused`). Composing reads ``off`` or ``1`` as a boolean without a word, so a
    boolean key's override is checked here, where its value is still the one given
    (:func:`armeta_rl.fields.reads_as_boolean`)."""
    from hydra import compose
    from hydra.errors import ConfigCompositionException, HydraException

    try:
        cfg = compose(config_name, overrides=job)
    except ConfigCompositionException as error:
        raise Refused(_composition_message(job, config_name, error)) from None
    except HydraException as error:
        raise Refused(" ".join(str(error).split())) from None
    _check_booleans(cfg, job)
    return cfg


def _check_booleans(cfg: DictConfig, job: list[str]) -> None:
    """Refuse an override of ``job`` that ``cfg`` took for a boolean only by reading it as one
    (:func:`armeta_rl.fields.reads_as_boolean`)."""
    from armeta_rl.fields import reads_as_boolean, type_words

    for arg in job:
        override = _parse(arg)
        key, value = override.key_or_group, override.value()
        node = _node(cfg, key)
        if reads_as_boolean(node, value):
            raise Refused(str(ConfigError(key, value, f"must be {type_words(node)}")))


def compose_run(job: list[str], hydra_words: list[str]) -> tuple[DictConfig, Path]:
    """A single run's config composed once, with its Hydra config (inside Hydra's initialized
    config dir): the job's config, and the directory Hydra will run it in (``hydra.run.dir``
    resolved now, its ``${now:...}`` included, so the CLI can check and lock it before Hydra
    writes there). A bad word is refused as :func:`compose_job` refuses the job's overrides
    ``job`` and :func:`check_hydra` the ``hydra.*`` words ``hydra_words``."""
    from hydra import compose
    from hydra.errors import HydraException
    from omegaconf import open_dict, read_write
    from omegaconf.errors import OmegaConfBaseException

    try:
        cfg = compose("train", overrides=[*job, *hydra_words], return_hydra_config=True)
    except (HydraException, OmegaConfBaseException) as error:
        compose_job(job)  # the job's own words refused first, as they are alone
        raise Refused(_hydra_message(hydra_words, _causes(error))) from None
    _check_booleans(cfg, job)
    run_dir = Path(OmegaConf.select(cfg, "hydra.run.dir"))
    with read_write(cfg), open_dict(cfg):
        del cfg["hydra"]
    return cfg, run_dir


def _composition_message(job: list[str], config_name: str, error: Exception) -> str:
    """One line for the override of ``job`` that Hydra could not compose: a missing key (with
    what is there and the likely one) or a value of the wrong type."""
    from hydra import compose

    text = str(error)
    for arg in job:
        key, value = arg.lstrip("+~").split("=", 1) if "=" in arg else (arg, "")
        if f"'{key}'" not in text and f"override {arg}" not in text:
            continue
        others = [a for a in job if a != arg]
        try:
            cfg = compose(config_name, overrides=others)
        except Exception:  # another override fails too: reported on its own
            break
        choices = [a for a in others if a.split("=")[0] in GROUPS]
        if not _has_key(cfg, key):
            return _unknown_key_message(cfg, key, value, choices)
        from armeta_rl.fields import type_words

        return f"config key '{key}' = {value}: must be {type_words(_node(cfg, key))}"
    return " ".join(text.split())


def check_hydra(args: Sequence[str], config_name: str) -> None:
    """Compose ``config_name`` with the ``hydra.*`` and ``hydra/<group>=`` words of ``args`` and
    its Hydra config, as Hydra will before its first job: a word Hydra would refuse (a value of
    the wrong type, a key its launcher lacks, a choice it does not have) is refused here as one
    line naming its key and value, where Hydra's own message spans several."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    words = hydra_words(args)
    if not words:
        return
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        try:
            compose(config_name, overrides=words, return_hydra_config=True)
        except (HydraException, OmegaConfBaseException) as error:
            raise Refused(_hydra_message(words, _causes(error))) from None


def hydra_words(args: Sequence[str]) -> list[str]:
    """The ``hydra.*`` and ``hydra/<group>=`` overrides of the command line ``args``."""
    return [a for a in args if "=" in a and not a.startswith("-")
            and _is_hydra_key(a.split("=", 1)[0].lstrip("+~"))]


def _causes(error: BaseException) -> str:
    """``error`` and the chain of its causes, a line each: Hydra prints the chain, and the
    reason is in it."""
    texts, cause = [], error
    while cause is not None:
        texts.append(str(cause))
        cause = cause.__cause__
    return "\n".join(texts)


def _hydra_message(words: Sequence[str], text: str) -> str:
    """One line for Hydra's refusal ``text`` of one of ``words``: its key and value, and what
    Hydra says is wrong or allows."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    options = []
    if any(line.startswith("Available options") for line in lines):
        start = next(i for i, line in enumerate(lines) if line.startswith("Available options"))
        options = [line for line in lines[start + 1:] if not line.startswith(
            ("Config search path", "provider="))]
        options = options[:next((i for i, o in enumerate(options) if " " in o), len(options))]
    reason = next((line for line in lines if not line.startswith((
        "Error merging override", "Could not override", "To append", "full_key:",
        "object_type=", "In '", "Available options", "Config search path", "provider="))),
        lines[0] if lines else "refused by Hydra")
    named = [word for word in words if f"override {word}" in text
             or f"{word.lstrip('+~').replace('=', '/', 1)}'" in text]
    for word in named or [word for word in reversed(words)
                          if word.lstrip("+~").split("=", 1)[0] in text]:
        key, value = word.lstrip("+~").split("=", 1)
        allowed = f"allowed: {', '.join(options)}" if options else reason
        return f"config key '{key}' = {value!r}: {allowed}"
    return " ".join(text.split())


def checked(cfg: DictConfig) -> TrainConfig:
    """The composed ``cfg`` validated (:func:`armeta_rl.config.validate`) with its method's
    names checked against the registries (:func:`armeta_rl.factory.check_method`)."""
    from armeta_rl.config import validate
    from armeta_rl.factory import check_method

    config = validate(cfg)
    check_method(config.method)
    return config


def check_jobs(args: Sequence[str]) -> dict[tuple[tuple[str, str], ...], TrainConfig]:
    """Compose and validate the ``armeta-train`` config of every job on the command line (each
    combination of a ``-m`` sweep), so that no job trains before every job's values are known to
    be good; returns their :class:`~armeta_rl.config.TrainConfig` by the job's overrides
    (:func:`job_key`).
    :class:`Refused` for the first bad one."""
    from hydra import initialize_config_dir


    jobs = job_overrides(args)
    configs = {}
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        for job in jobs:
            where = f" (job {' '.join(job)})" if len(jobs) > 1 else ""
            try:
                config = checked(compose_job(job))
            except Refused as refused:
                raise Refused(f"{refused}{where}") from None
            except ConfigError as error:
                raise Refused(f"{error}{where}") from None
            configs[job_key(job)] = config
    return configs


def job_key(overrides: Sequence[str]) -> tuple[tuple[str, str], ...]:
    """The overrides of a job as the values they set, by key: the same for the words a command
    line gave and the words Hydra hands the job (which writes ``false`` as ``False``)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return tuple((o.get_key_element(), str(o.value()))
                 for o in OverridesParser.create().parse_overrides(list(overrides)))


RESUMABLE = ("trainer.iterations", "trainer.stop_at", "device")
"""The keys a resumed run may change that change what it computes: train longer, stop earlier,
continue on another device (its checkpoint loads there)."""
NO_RESULT_KEYS = ("logger", "logger.kind", "logger.project", "logger.tracking_uri",
                  "trainer.progress", "trainer.log_every", "trainer.density_every",
                  "trainer.keep_freed_memory", "trainer.stop_signals", "threads", "adopt")
"""The keys a resumed run may change that change no result (``eval.json`` and every logged
value stay those of the uninterrupted run): where and how often it logs and draws, the progress
bar, the allocator, the stop signals, torch's thread count (which the seeded benchmark
families were measured not to change: tests/test_faults.py) and ``adopt`` (taking checkpoints
that record no run as the run's own)."""


def make_job(overrides: Sequence[str], composed: DictConfig | None = None,
             run_dir: Path | None = None) -> Job:
    """The one door into a run: the :class:`~armeta_rl.job.Job` of a command line's, a sweep
    job's or a Python caller's ``overrides``.

    With ``resume=<dir>`` among them (or in ``composed``), the run saved there continues: its
    saved config, read once, with the changes a resume may make (:func:`resumed`), in that
    directory. Otherwise ``composed`` (the config composed for ``overrides``; composed here when
    not given) is validated and its method's names checked (:func:`checked`), for a run in
    ``run_dir``.

    Raises:
        Refused: an override that does not compose or that a resume cannot take.
        ConfigError: a bad value.
    """
    from armeta_rl.job import Job

    resume = (composed.resume if composed is not None
              else next((a.split("=", 1)[1] for a in reversed(overrides)
                         if a.startswith("resume=")), None))
    if resume:
        return resumed(resume, overrides)
    if composed is None:
        from hydra import initialize_config_dir

        with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
            composed = compose_job(list(overrides))
    if run_dir is None:
        raise TypeError("a new run's job needs its run_dir")
    return Job(checked(composed), run_dir)


def resumed(run_dir: str, overrides: Sequence[str]) -> Job:
    """The job of the run resumed from ``run_dir`` with ``overrides``, its config validated: its
    saved config (read once), ``trainer.stop_at`` and ``adopt`` as given (default none, false: a
    resume's own), ``trainer.iterations`` raised and ``device`` and the keys of
    :data:`NO_RESULT_KEYS` changed if given; the job names each key of :data:`NO_RESULT_KEYS` it
    changes. Any other override, or fewer iterations, is refused (:class:`Refused`; a bad
    value: :class:`ConfigError`)."""
    from armeta_rl.config import load_run_config, validate
    from armeta_rl.job import Job

    config_dir()  # the learners' and risk principles' sections, which the saved config fills
    saved = load_run_config(run_dir, "resume")
    changes: dict[str, Any] = {"resume": run_dir, "adopt": False, "trainer": {"stop_at": None}}
    for arg in overrides:
        override = _parse(arg)
        name = override.key_or_group
        if name == "resume" or _is_hydra_key(name):
            continue
        value = arg.split("=", 1)[1] if "=" in arg else ""
        allowed = (*RESUMABLE, *NO_RESULT_KEYS)
        if override.is_add() or override.is_delete() or name not in allowed:
            raise Refused(f"config key '{name.lstrip('+~')}' = {value}: cannot change on resume "
                          f"(only {', '.join(allowed)} can); train a new run to change it")
        if name == "logger":  # a group: its file's keys
            chosen = OmegaConf.load(config_files() / "logger" / f"{value}.yaml")
            changes["logger"] = {"project": None, "tracking_uri": None,
                                 **OmegaConf.to_container(chosen)}
            continue
        *groups, leaf = name.split(".")
        node = changes
        for group in groups:
            node = node.setdefault(group, {})
        node[leaf] = override.value()
    new = changes["trainer"].get("iterations", saved.trainer.iterations)
    if isinstance(new, int) and not isinstance(new, bool) and new < saved.trainer.iterations:
        raise Refused(f"config key 'trainer.iterations' = {new}: must be >= "
                       f"{saved.trainer.iterations} on resume (a run can train longer, not "
                       "shorter)")
    cfg = _merged(saved, changes)
    return Job(validate(cfg), Path(run_dir), OmegaConf.to_container(saved, resolve=True),
               tuple(changed_on_resume(saved, cfg)))


def changed_on_resume(saved: DictConfig, cfg: DictConfig) -> list[str]:
    """``key=value`` of every key of :data:`NO_RESULT_KEYS` whose value ``cfg`` changes."""
    changed = []
    for name in NO_RESULT_KEYS:
        old, new = (OmegaConf.select(c, name) for c in (saved, cfg))
        if old != new and not isinstance(new, DictConfig):
            shown = new if not isinstance(new, (list, tuple, ListConfig)) else list(new)
            changed.append(f"{name}={shown}")
    return changed


def _merged(saved: DictConfig, changes: dict[str, Any]) -> DictConfig:
    from omegaconf.errors import OmegaConfBaseException

    from armeta_rl.fields import config_error

    try:
        return OmegaConf.merge(saved, changes)
    except OmegaConfBaseException as error:
        raise config_error(error) from None


def _report_errors(prog: str, task: Callable[[DictConfig], None]) -> Callable[[DictConfig], None]:
    """Run ``task`` turning the package's user errors into one line and their exit code
    (:func:`failure`). A job of a ``run_list`` sweep (``armeta-reproduce``) raises
    :class:`~armeta_rl.errors.JobFailed` with that code instead of exiting, so that the jobs
    beside it run on; the sweeper exits with the code once all ran."""

    def wrapped(cfg: DictConfig) -> None:
        try:
            task(cfg)
        except Exception as error:
            status = failure(error)
            if status is None:
                raise
            code, line = status
            print(f"{prog}: {line}", file=sys.stderr)
            if _in_run_list_sweep():
                raise JobFailed(code) from None
            sys.exit(code)

    return wrapped


def failure(error: BaseException) -> tuple[int, str] | None:
    """The exit code of ``error`` and the line that says it: the one table of the codes of
    ``armeta-train`` and ``armeta-eval``. 2: a refused value or command, or an allocation that
    failed; 1: a run that diverged, lost a collection worker or could not write; a stopped run's
    own code (:mod:`armeta_rl.preemption`). ``None`` for any other error: a bug, whose traceback
    is the report."""
    if isinstance(error, (ConfigError, Refused)):
        return getattr(error, "code", 2), f"error: {error}"
    if isinstance(error, RunStopped):  # not an error: a code a requeue acts on
        return error.code, str(error)
    if isinstance(error, (TrainingDiverged, CollectionFailed)):
        return 1, f"error: training stopped: {error}"
    if isinstance(error, RunDirectoryError):
        return 1, f"error: {error}"
    if isinstance(error, KeyboardInterrupt):  # Ctrl-C where no run stops cleanly
        return EXIT_INTERRUPTED, "interrupted (SIGINT)"
    if isinstance(error, (MemoryError, RuntimeError, OSError)) and out_of_memory(error):
        return 2, f"error: {OUT_OF_MEMORY}"
    if isinstance(error, OSError):
        return 1, "error: " + f"{error.strerror or error}: {error.filename or ''}".rstrip(": ")
    return None


OUT_OF_MEMORY = ("out of memory: this process may not allocate what the run needs (a memory "
                 "limit, or sizes too large for this machine): smaller sizes, or more memory")


def out_of_memory(error: BaseException) -> bool:
    """Whether ``error`` is an allocation that failed (Python's ``MemoryError``, torch's CPU or
    CUDA allocator)."""
    if isinstance(error, OSError):
        return error.errno == errno.ENOMEM
    text = str(error)
    return isinstance(error, MemoryError) or "can't allocate memory" in text or (
        "out of memory" in text.lower())


def _in_run_list_sweep() -> bool:
    """Whether this job belongs to a ``hydra/sweeper=run_list`` multirun."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from hydra_plugins.armeta_run_list.run_list_sweeper import RunListSweeperConf

    if not HydraConfig.initialized():
        return False
    hydra_cfg = HydraConfig.get()
    return (hydra_cfg.mode == RunMode.MULTIRUN
            and hydra_cfg.sweeper.get("_target_") == RunListSweeperConf._target_)


def _train_task(job: Job) -> None:
    """Train (or resume) ``job``, stopping cleanly on ``trainer.stop_signals`` and SIGINT
    (:mod:`armeta_rl.preemption`): the signal becomes the process's stop request, which the game
    loop reads. The keys a resume changed (:attr:`Job.taken`) are said first."""
    from armeta_rl.allocator import keep_freed_memory
    from armeta_rl.errors import RunStopped
    from armeta_rl.preemption import PROCESS, listening
    from armeta_rl.trainers.training import run_training

    if job.taken:
        print(f"resuming {job.run_dir} with {', '.join(job.taken)} (they change no result)")
    if PROCESS.requested:  # a later job of a sweep worker that was asked to stop
        raise RunStopped(f"not started: this process received {PROCESS.name}; the same command "
                         "starts it", PROCESS.exit_code)
    trainer = job.config.trainer
    if trainer.keep_freed_memory:
        keep_freed_memory()
    with listening(trainer.stop_signals) as stop:
        run_training(job, stop=stop)


def _sweep_task(checked_here: dict[tuple[tuple[str, str], ...], TrainConfig]
                ) -> Callable[[DictConfig], None]:
    """The task of every job of a ``-m`` sweep: the job (:func:`make_job`) of the config Hydra
    composed for it, in the directory Hydra gave it, trained (:func:`_train_task`). A job whose
    config this process validated before Hydra started (``checked_here``, by its overrides,
    :func:`job_key`: a basic sweep's) and that runs in this process takes that config; a job a
    launcher runs in another process (joblib, Ray, Slurm) validates its own, on its machine, as
    does a ``run_list`` sweep's (``armeta-reproduce`` checked its runs before launching)."""
    import os

    host = os.getpid()

    def task(cfg: DictConfig) -> None:
        from hydra.core.hydra_config import HydraConfig

        from armeta_rl.job import Job

        hydra_cfg = HydraConfig.get()
        overrides = list(hydra_cfg.overrides.task)
        run_dir = Path(hydra_cfg.runtime.output_dir)
        config = checked_here.get(job_key(overrides)) if os.getpid() == host else None
        if config is not None and not cfg.resume:
            _train_task(Job(config, run_dir))
        else:
            _train_task(make_job(overrides, cfg, run_dir))

    return task


def _run_hydra(argv: list[str], config_name: str, task: Callable[[DictConfig], None]) -> None:
    """Hydra's command line (``hydra.main``) on ``argv``: Hydra's entry point reads its words
    from ``sys.argv``, which holds them while it runs."""
    import hydra

    main = hydra.main(config_path=str(config_dir()), config_name=config_name,
                      version_base=None)(task)
    program = sys.argv[:1] or ["armeta"]
    saved, sys.argv = sys.argv, [*program, *argv]
    try:
        main()
    finally:
        sys.argv = saved


def _exit_code(main: Callable[[list[str]], None], prog: str, argv: list[str]) -> int:
    """``main(argv)``'s exit code: 0, the code of its ``SystemExit``, or 2 (1) with one line
    for a refused command (a failed run)."""
    try:
        main(argv)
    except SystemExit as stop:
        return stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    except (Exception, KeyboardInterrupt) as error:  # e.g. importing under a memory limit
        status = failure(error)
        if status is None:
            raise
        code, line = status
        print(f"{prog}: {line}", file=sys.stderr)
        return code
    return 0


def _command(main: Callable[[list[str]], None], prog: str, argv: list[str] | None) -> int:
    """``main``'s exit code on ``argv``; with ``argv`` ``None``, on ``sys.argv[1:]``, exiting."""
    if argv is not None:
        return _exit_code(main, prog, list(argv))
    sys.exit(_exit_code(main, prog, sys.argv[1:]))


def _without_checks(args: list[str], prog: str, config_name: str,
                    task: Callable[[DictConfig], None], groups: tuple[str, ...], usage: str
                    ) -> bool:
    """Answer ``--help`` (:func:`_print_help`) or hand Hydra a flag whose words are no
    overrides (``-sc install=bash``, ``--hydra-help``); whether it did."""
    if any(a in ("--help", "-h") for a in args):
        _print_help(prog, config_name, groups, usage)
        return True
    if any(a in _UNCHECKED_FLAGS for a in args):
        _run_hydra(args, config_name, task)
        return True
    return False


def _print_help(prog: str, config_name: str, groups: tuple[str, ...], usage: str) -> None:
    """``--help``: the usage, the groups a command line chooses from and where to see the
    composed config. It reads only the config folder: composing the config would import every
    learner (torch, TorchRL, MuJoCo) for a page of text, which ``--cfg job`` prints instead."""
    lines = [f"{prog}: {usage}", "", "Configuration groups (group=option):"]
    lines += [f"  {group}: {', '.join(group_choices(group))}" for group in groups] or ["  none"]
    lines += ["", f"Config: configs/{config_name}.yaml and the dataclasses it lists; override any "
              "key with key=value, add one with +key=value (docs/configuration.md).",
              f"The composed config of a command line, every key with its value: {prog} "
              "[overrides] --cfg job",
              "Hydra's own flags (-m, --cfg job, -sc install=bash, ...): --hydra-help"]
    print("\n".join(lines))


def train(argv: list[str] | None = None) -> int:
    """``armeta-train``: train a method on a benchmark (see ``configs/train.yaml``); returns the
    exit code of the command line ``argv``. Without ``argv`` it is the program: it runs
    ``sys.argv[1:]`` and exits with that code.

    Every job's config is composed and validated before Hydra starts. A single run's directory
    is checked and locked then too (Hydra writes ``.hydra/`` and its log there); a run refused
    before it wrote a checkpoint removes the directory it created. ``-m`` jobs lock their own
    directories.
    """
    return _command(_train, "armeta-train", argv)


def _train(args: list[str]) -> None:
    prog = "armeta-train"
    if _without_checks(args, prog, "train", _report_errors(prog, _sweep_task({})), GROUPS,
                       "train a method on a benchmark (armeta-train [group=option ...] "
                       "[key=value ...] [-m])"):
        return
    for arg in args:
        name, _, value = arg.partition("=")
        if name in ("hydra.run.dir", "hydra.sweep.dir") and not value.strip():
            raise Refused(f"config key '{name}' = '': must name a directory")
    resume = next((a.split("=", 1)[1] for a in args if a.startswith("resume=")), None)
    multirun = any(a in ("-m", "--multirun") for a in args)
    no_run = multirun or any(a.split("=")[0] in _NO_RUN_FLAGS for a in args)
    if resume:
        if multirun:
            raise Refused(f"config key 'resume' = {resume}: resumes one run, not a -m sweep")
        job = make_job([a for a in args if not a.startswith("-")])
        # the run's job log stays in its own directory, whatever hydra.run.dir says
        args = [a for a in args if not a.startswith(("hydra.run.dir=", "hydra.output_subdir="))]
        check_hydra(args, "train")
        args += [f"hydra.run.dir={resume}", "hydra.output_subdir=null"]
    elif no_run:
        # a run_list sweep's jobs are in its jobs file, checked by armeta-reproduce
        listed = "hydra/sweeper=run_list" in args and job_overrides(args) == [[]]
        checked_here = {} if listed else check_jobs(args)
        check_hydra(args, "train")
    else:
        job = _new_job(args)
    if no_run:
        _run_hydra(args, "train", _report_errors(prog, _sweep_task(
            {} if resume else checked_here)))
        return
    from armeta_rl.trainers.run_dir import (  # torch: after the checks
        check_contents,
        check_run_dir,
        run_lock,
    )

    run_dir = job.run_dir
    # Hydra composes the config again for its job; the run takes the one checked here
    task = _report_errors(prog, lambda _composed: _train_task(job))
    key = "resume" if resume else "hydra.run.dir"
    check_run_dir(run_dir, key)
    if resume:  # before Hydra appends to its job log there
        check_contents(run_dir, key)
    given = [a for a in args if a.startswith("hydra.run.dir=")]
    if not given or "${" in given[-1]:  # pin what Hydra would resolve again (its ${now:...})
        args = [a for a in args if a not in given] + [f"hydra.run.dir={run_dir}"]
    created = _first_missing(run_dir)
    with ExitStack() as stack:
        stack.enter_context(run_lock(run_dir, key))
        try:
            _run_hydra(args, "train", task)
        except SystemExit as exit_:
            if exit_.code == 2 and created and not (run_dir / "checkpoints").exists():
                _remove_run_dir(created)
            raise


def _new_job(args: list[str]) -> Job:
    """The job of a new single run's command line ``args``: its config composed once with its
    Hydra config (:func:`compose_run`) and validated (:func:`make_job`), in the directory Hydra
    will run it in. A command line of several jobs (a value with commas) is refused, after each
    job's config is checked."""
    from hydra import initialize_config_dir

    jobs = job_overrides(args)
    if len(jobs) > 1:
        check_jobs(args)
        check_hydra(args, "train")
        raise Refused(f"a command line of {len(jobs)} jobs (a value with commas): add -m "
                      "to run them all; a list value is written key=[a,b]")
    (job,) = jobs
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        cfg, run_dir = compose_run(job, hydra_words(args))
        return make_job(job, cfg, run_dir)


def _first_missing(path: Path) -> Path | None:
    """The outermost of ``path`` and its parents that does not exist yet (``None``: it exists),
    so a refused run removes every directory its command created, not only the run's own."""
    missing = None
    for candidate in (path, *path.parents):
        if candidate.exists():
            break
        missing = candidate
    return missing


def _remove_run_dir(run_dir: Path) -> None:
    """Delete a run directory (with the parents) this command created for a run it then refused."""
    import shutil

    shutil.rmtree(run_dir, ignore_errors=True)


def _eval_task(cfg: DictConfig) -> None:
    """Score the runs ``cfg`` names: each run's saved config, with the command line's ``device``
    and ``eval.*``, validated once (:func:`armeta_rl.trainers.players.saved_run`), the run
    directories first, each named as itself, then the report's path derived from them."""
    from armeta_rl.trainers.evaluation import format_table
    from armeta_rl.trainers.players import saved_run
    from armeta_rl.trainers.report import evaluate_runs
    from armeta_rl.trainers.run_dir import write_text_atomically

    if not isinstance(cfg.initial, bool):
        raise ConfigError("initial", cfg.initial, "must be true or false")
    if not isinstance(cfg.adopt, bool):
        raise ConfigError("adopt", cfg.adopt, "must be true or false")
    overrides = {k: v for k, v in OmegaConf.to_container(cfg.eval).items() if v is not None}
    learner = saved_run(cfg.learner, "learner", cfg.device,
                        {"eval": overrides, "adopt": cfg.adopt})
    adversary = (None if cfg.adversary is None
                 else saved_run(cfg.adversary, "adversary", cfg.device, {"adopt": cfg.adopt}))
    shifts = OmegaConf.to_container(cfg.shifts) if OmegaConf.is_list(cfg.shifts) else cfg.shifts
    suffix = ("" if cfg.adversary is None else f"_vs_{Path(cfg.adversary).name}") or (
        "" if shifts is None else "_shifts")
    out = Path(cfg.out) if cfg.out else Path(cfg.learner) / f"eval{suffix}.json"
    check_writable(out, "out")
    report = evaluate_runs(cfg.learner, learner, cfg.adversary, adversary, shifts, cfg.initial)
    write_text_atomically(out, json.dumps(report, indent=2) + "\n")
    print(format_table(report))
    print(f"written: {out}")


def check_writable(path: Path, key: str) -> None:
    """Refuse an output file that cannot be written, before the work that fills it: its folder
    is tried by creating and removing a hidden file there (the report is written atomically,
    through such a sibling)."""
    from armeta_rl.trainers.run_dir import unwritable

    if path.is_dir():
        raise ConfigError(key, str(path), "is a directory, not a file")
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise ConfigError(key, str(path), "is not a regular file (a link, a device, a pipe): "
                          "allowed: a new name or a regular file, which the report replaces")
    parent = path.parent
    if not parent.is_dir():
        raise ConfigError(key, str(path), f"cannot be written: {parent} is not a directory")
    problem = unwritable(parent)
    if problem is not None:
        raise ConfigError(key, str(path), f"cannot be written in {parent} ({problem})")


def evaluate(argv: list[str] | None = None) -> int:
    """``armeta-eval``: score a saved learner on p0, on a saved adversary and on its benchmark's
    shift suite; returns the exit code of the command line ``argv``. Without ``argv`` it is the
    program: it runs ``sys.argv[1:]`` and exits with that code."""
    return _command(_evaluate, "armeta-eval", argv)


def _evaluate(args: list[str]) -> None:
    prog = "armeta-eval"
    task = _report_errors(prog, _eval_task)
    if _without_checks(args, prog, "eval", task, (), "score a saved learner on p0, on a "
                       "saved adversary and on its benchmark's shift suite (armeta-eval "
                       "learner=<run dir> [adversary=<run dir>] [shifts=all|[name,...]] "
                       "[eval.rollouts=R] [eval.n_tasks=...] [out=<file>])"):
        return
    multirun = "-m" in args or "--multirun" in args  # a sweep's jobs carry their own learner=
    if not multirun and not any(a.startswith("learner=") for a in args):
        raise Refused("config key 'learner' is missing: give the run directory to score, "
                       "e.g. armeta-eval learner=runs/... adversary=runs/...")
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        for job in job_overrides(args, groups=()):
            compose_job(job, "eval")
    check_hydra(args, "eval")
    _run_hydra(args, "eval", task)
