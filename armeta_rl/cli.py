"""Console entry points ``armeta-train`` and ``armeta-eval`` (Hydra).

Bad input ends with one line naming the config key, the value and what is allowed, and exit
code 2. Overrides (group choices such as ``benchmark=`` and the keys of the others) and the values
of every job (against the schema in :mod:`armeta_rl.config`) are checked before Hydra starts; a
single run's directory is checked and locked then too, so a refused command writes nothing. A
run stopped by a diverged loss or a failed write ends with one line and exit code 1. See
docs/configuration.md.
"""

from __future__ import annotations

import difflib
import functools
import itertools
import json
import sys
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any, NoReturn

import hydra
from omegaconf import DictConfig, OmegaConf

GROUPS = ("benchmark", "method", "logger")
_ABSENT = object()


def config_dir() -> Path:
    """The Hydra config directory, ready to compose from: ``train.yaml`` composes
    ``learner_options`` and ``risk_options`` and resolves ``${method_name:...}``, which
    :mod:`armeta_rl.config` stores in Hydra's ConfigStore and registers with OmegaConf when
    imported. That import loads the learners (torch), so it is made here, where configs are
    composed, and not by ``import armeta_rl`` or by importing this module."""
    import armeta_rl.config  # noqa: F401

    return config_files()


def config_files() -> Path:
    """Where the config files are: packaged in a wheel, or the repository's ``configs/``."""
    packaged = Path(__file__).parent / "configs"
    return packaged if packaged.is_dir() else Path(__file__).resolve().parents[1] / "configs"


def _fail(prog: str, message: str, code: int = 2) -> NoReturn:
    print(f"{prog}: error: {message}", file=sys.stderr)
    sys.exit(code)


def group_choices(group: str) -> list[str]:
    """Names of the configs available for a config group, e.g. the benchmarks."""
    return sorted(path.stem for path in (config_files() / group).glob("*.yaml"))


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


def check_overrides(
    args: list[str], prog: str, config_name: str, groups: tuple[str, ...] = ()
) -> None:
    """Reject with one line, before Hydra starts, an override Hydra cannot parse, an unknown choice
    of a config group in ``groups`` (``benchmark=``, ``method=``, ``logger=``; also inside ``-m``
    sweeps), and an override of a key the composed config does not have (a typo such as
    ``trainer.iteratons=5``).

    The config is composed for every combination of the group choices on the command line, so a
    key is accepted when the benchmark or method that defines it is chosen. Adding (``+key=``),
    deleting (``~key``) and ``hydra.*`` overrides are left to Hydra.
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    chosen: dict[str, list[str]] = {}
    changes = []
    for arg in args:
        if arg.startswith("-") or "=" not in arg:
            continue
        try:
            (override,) = parser.parse_overrides([arg])
        except HydraException as error:
            reason = str(error).splitlines()[0]
            _fail(prog, f"cannot read the override {arg!r}: {reason}")
        key = override.key_or_group
        if override.is_delete() or key.split(".")[0].split("/")[0] == "hydra":
            continue
        if key in groups:
            values = override.sweep_string_iterator() if override.is_sweep_override() else [
                override.value()
            ]
            chosen[key] = [str(choice) for choice in values]
            allowed = group_choices(key)
            for choice in chosen[key]:
                if choice not in allowed:
                    _fail(prog, f"config key '{key}' = {choice!r}: allowed: {', '.join(allowed)}")
        elif not override.is_add():
            changes.append((key, arg.split("=", 1)[1]))
    if not changes:
        return
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        for combination in itertools.product(*chosen.values()):
            choices = [f"{group}={choice}" for group, choice in zip(chosen, combination)]
            cfg = compose(config_name, overrides=choices)
            for key, value in changes:
                if not _has_key(cfg, key):
                    _fail(prog, _unknown_key_message(cfg, key, value, choices))


def _parse(arg: str, prog: str) -> Any:
    """The Hydra override ``arg`` parses to, or one line and exit code 2."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        (override,) = OverridesParser.create().parse_overrides([arg])
    except HydraException as error:
        _fail(prog, f"cannot read the override {arg!r}: {str(error).splitlines()[0]}")
    return override


def _is_hydra_key(key: str) -> bool:
    return key.split(".")[0].split("/")[0] == "hydra"


def job_overrides(args: list[str], prog: str) -> list[list[str]]:
    """The config overrides (not ``hydra.*``) of every job the command line starts: one list for
    each combination of the values of ``-m`` sweeps such as ``trainer.iterations=5,0``."""
    per_arg = []
    for arg in args:
        if arg.startswith("-") or "=" not in arg:
            continue
        override = _parse(arg, prog)
        if _is_hydra_key(override.key_or_group):
            continue
        if override.is_sweep_override():
            name = arg.split("=", 1)[0]
            per_arg.append([f"{name}={value}" for value in override.sweep_string_iterator()])
        else:
            per_arg.append([arg])
    return [list(job) for job in itertools.product(*per_arg)]


def check_values(args: list[str], prog: str) -> None:
    """Compose the ``armeta-train`` config of every job on the command line (each combination of
    a ``-m`` sweep) and check it against the schema, so that no job trains before every job's
    values are known to be good. One line and exit code 2 for the first bad one."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException

    from armeta_rl.config import check_config
    from armeta_rl.errors import ConfigError

    jobs = job_overrides(args, prog)
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        for job in jobs:
            where = f" (job {' '.join(job)})" if len(jobs) > 1 else ""
            try:
                check_config(compose("train", overrides=job))
            except HydraException as error:
                _fail(prog, " ".join(str(error).split()) + where)
            except ConfigError as error:
                _fail(prog, f"{error}{where}")


RESUMABLE = ("trainer.iterations", "trainer.stop_at", "device")
"""The keys a resumed run may change that change what it computes: train longer, stop earlier,
continue on another device (its checkpoint loads there)."""
NO_RESULT_KEYS = ("logger", "logger.kind", "logger.project", "trainer.progress",
                  "trainer.log_every", "trainer.density_every", "trainer.keep_freed_memory",
                  "trainer.stop_signals", "threads")
"""The keys a resumed run may change that change no result (``eval.json`` and every logged
value stay those of the uninterrupted run): where and how often it logs and draws, the progress
bar, the allocator, the stop signals, and torch's thread count (which the seeded benchmark
families were measured not to change: tests/test_faults.py)."""


def resume_config(run_dir: str, overrides: list[str], prog: str) -> DictConfig:
    """The config a run resumed from ``run_dir`` with ``overrides`` continues under: its saved
    config, ``trainer.stop_at`` as given (default none), ``trainer.iterations`` raised and
    ``device`` and the keys of :data:`NO_RESULT_KEYS` changed if given. Any other override, or
    fewer iterations, is refused (one line, exit code 2)."""
    from armeta_rl.config import check_config, load_run_config

    saved = _checked(prog, load_run_config, run_dir, "resume")
    changes: dict[str, Any] = {"resume": run_dir, "trainer": {"stop_at": None}}
    for arg in overrides:
        override = _parse(arg, prog)
        name = override.key_or_group
        if name == "resume" or _is_hydra_key(name):
            continue
        value = arg.split("=", 1)[1] if "=" in arg else ""
        if override.is_add() or override.is_delete() or name not in (*RESUMABLE,
                                                                       *NO_RESULT_KEYS):
            _fail(prog, f"config key '{name.lstrip('+~')}' = {value}: cannot change on resume "
                        f"(only {', '.join((*RESUMABLE, *NO_RESULT_KEYS))} can); train a new "
                        "run to change it")
        if name == "logger":  # a group: its file's keys
            chosen = OmegaConf.load(config_files() / "logger" / f"{value}.yaml")
            changes["logger"] = {"project": None, **OmegaConf.to_container(chosen)}
            continue
        *groups, leaf = name.split(".")
        node = changes
        for group in groups:
            node = node.setdefault(group, {})
        node[leaf] = override.value()
    new = changes["trainer"].get("iterations", saved.trainer.iterations)
    if isinstance(new, int) and not isinstance(new, bool) and new < saved.trainer.iterations:
        _fail(prog, f"config key 'trainer.iterations' = {new}: must be >= "
                    f"{saved.trainer.iterations} on resume (a run can train longer, not shorter)")
    cfg = OmegaConf.merge(saved, changes)
    _checked(prog, check_config, cfg)
    return cfg


def changed_on_resume(saved: DictConfig, cfg: DictConfig) -> list[str]:
    """``key=value`` of every key of :data:`NO_RESULT_KEYS` whose value ``cfg`` changes."""
    changed = []
    for name in NO_RESULT_KEYS:
        old, new = (OmegaConf.select(c, name) for c in (saved, cfg))
        if old != new and not isinstance(new, DictConfig):
            shown = new if not isinstance(new, (list, tuple)) else list(new)
            changed.append(f"{name}={shown}")
    return changed


def _checked(prog: str, check: Callable[..., Any], *args: Any) -> Any:
    """``check(*args)``, with a :class:`ConfigError` as one line and exit code 2."""
    from armeta_rl.errors import ConfigError

    try:
        return check(*args)
    except ConfigError as error:
        _fail(prog, str(error))


def _guarded(prog: str, task: Callable[[DictConfig], None]) -> Callable[[DictConfig], None]:
    """Run ``task`` turning the package's user errors into one line and an exit code: 2 for a
    bad value, 1 for a run that diverged or a disk that failed it. A job of a ``run_list`` sweep
    (``armeta-reproduce``) raises :class:`~armeta_rl.errors.JobFailed` with that code instead of
    exiting, so that the jobs beside it run on; the sweeper exits with the code once all ran."""

    def wrapped(cfg: DictConfig) -> None:
        from armeta_rl.errors import JobFailed

        try:
            _report_errors(prog, task, cfg)
        except SystemExit as stop:
            if stop.code and _in_run_list_sweep():
                raise JobFailed(stop.code if isinstance(stop.code, int) else 1) from None
            raise

    return wrapped


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


def _report_errors(prog: str, task: Callable[[DictConfig], None], cfg: DictConfig) -> None:
    """Run ``task`` on ``cfg``; a user error exits with its one line (:func:`_guarded`)."""
    from armeta_rl.errors import (
        CollectionFailed,
        ConfigError,
        RunDirectoryError,
        RunStopped,
        TrainingDiverged,
    )

    try:
        task(cfg)
    except ConfigError as error:
        _fail(prog, str(error))
    except RunStopped as error:  # not an error: one line, and a code a requeue acts on
        print(f"{prog}: {error}", file=sys.stderr)
        sys.exit(error.code)
    except (TrainingDiverged, CollectionFailed) as error:
        _fail(prog, f"training stopped: {error}", code=1)
    except RunDirectoryError as error:
        _fail(prog, str(error), code=1)
    except OSError as error:
        _fail(prog, f"{error.strerror or error}: {error.filename or ''}".rstrip(": "), code=1)


def _train_task(cfg: DictConfig) -> None:
    """Train (or resume) one run, stopping cleanly on ``trainer.stop_signals`` and SIGINT
    (:mod:`armeta_rl.preemption`): the signal becomes the process's stop request, which the game
    loop reads."""
    from hydra.core.hydra_config import HydraConfig

    from armeta_rl.allocator import keep_freed_memory
    from armeta_rl.config import load_run_config
    from armeta_rl.errors import RunStopped
    from armeta_rl.preemption import PROCESS, listening
    from armeta_rl.trainers.training import run_training

    if cfg.resume:
        saved = load_run_config(cfg.resume, "resume")
        cfg = resume_config(cfg.resume, list(HydraConfig.get().overrides.task), "armeta-train")
        run_dir = Path(cfg.resume)
        taken = changed_on_resume(saved, cfg)
        if taken:
            print(f"resuming {run_dir} with {', '.join(taken)} (they change no result)")
    else:
        run_dir = Path(HydraConfig.get().runtime.output_dir)
    if PROCESS.requested:  # a later job of a sweep worker that was asked to stop
        raise RunStopped(f"not started: this process received {PROCESS.name}; the same command "
                         "starts it", PROCESS.exit_code)
    if cfg.trainer.keep_freed_memory:
        keep_freed_memory()
    with listening(cfg.trainer.stop_signals) as stop:
        run_training(cfg, run_dir, stop=stop)


_NO_RUN_FLAGS = ("--cfg", "-c", "--help", "-h", "--hydra-help", "--info", "-i",
                 "--shell-completion", "-sc", "--resolve")


def planned_run_dir(args: list[str]) -> Path:
    """The directory Hydra will run a single job in: ``hydra.run.dir`` resolved now (its
    ``${now:...}`` included), so the CLI can check and lock it before Hydra writes there."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        overrides = [a for a in args if not a.startswith("-") and "=" in a]
        cfg = compose("train", overrides=overrides, return_hydra_config=True)
        return Path(OmegaConf.select(cfg, "hydra.run.dir"))


def _interruptible(prog: str) -> Callable[[Callable[[], None]], Callable[[], None]]:
    """A command that Ctrl-C ends with one line and exit code 130 where no run is stopping
    cleanly (:mod:`armeta_rl.preemption` handles it while a run trains)."""

    def wrap(command: Callable[[], None]) -> Callable[[], None]:
        @functools.wraps(command)
        def run() -> None:
            from armeta_rl.preemption import EXIT_INTERRUPTED

            try:
                command()
            except KeyboardInterrupt:
                _fail(prog, "interrupted (SIGINT)", code=EXIT_INTERRUPTED)

        return run

    return wrap


@_interruptible("armeta-train")
def train() -> None:
    """``armeta-train``: train a method on a benchmark (see ``configs/train.yaml``).

    A single run's directory is checked and locked before Hydra starts (Hydra writes ``.hydra/``
    and its log there); a run refused before it wrote a checkpoint removes the directory it
    created. ``-m`` jobs lock their own directories.
    """
    from armeta_rl.trainers.run_dir import check_run_dir, run_lock

    prog = "armeta-train"
    args = sys.argv[1:]
    for arg in args:
        name, _, value = arg.partition("=")
        if name in ("hydra.run.dir", "hydra.sweep.dir") and not value.strip():
            _fail(prog, f"config key '{name}' = '': must name a directory")
    check_overrides(args, prog, "train", GROUPS)
    resume = next((a.split("=", 1)[1] for a in args if a.startswith("resume=")), None)
    multirun = any(a in ("-m", "--multirun") for a in args)
    if resume:
        if multirun:
            _fail(prog, f"config key 'resume' = {resume}: resumes one run, not a -m sweep")
        resume_config(resume, [a for a in args if not a.startswith("-")], prog)
        if not any(a.startswith("hydra.run.dir=") for a in args):
            args += [f"hydra.run.dir={resume}", "hydra.output_subdir=null"]
    else:
        check_values(args, prog)
    main = hydra.main(version_base=None, config_path=str(config_dir()), config_name="train")
    if multirun or any(a.split("=")[0] in _NO_RUN_FLAGS for a in args):
        sys.argv = [sys.argv[0], *args]
        main(_guarded(prog, _train_task))()
        return
    run_dir = Path(resume) if resume else planned_run_dir(args)
    key = "resume" if resume else "hydra.run.dir"
    _checked(prog, check_run_dir, run_dir, key)
    given = [a for a in args if a.startswith("hydra.run.dir=")]
    if not given or "${" in given[-1]:  # pin what Hydra would resolve again (its ${now:...})
        args = [a for a in args if a not in given] + [f"hydra.run.dir={run_dir}"]
    sys.argv = [sys.argv[0], *args]
    created = _first_missing(run_dir)
    with ExitStack() as stack:
        _checked(prog, stack.enter_context, run_lock(run_dir, key))
        try:
            main(_guarded(prog, _train_task))()
        except SystemExit as exit_:
            if exit_.code == 2 and created and not (run_dir / "checkpoints").exists():
                _remove_run_dir(created)
            raise


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
    from armeta_rl.config import load_run_config
    from armeta_rl.trainers.evaluation import format_table
    from armeta_rl.trainers.report import cross_evaluate
    from armeta_rl.trainers.run_dir import write_text_atomically

    load_run_config(cfg.learner, "learner")  # the run directories first, each named as itself,
    if cfg.adversary is not None:            # then the report's path derived from them
        load_run_config(cfg.adversary, "adversary")
    suffix = "" if cfg.adversary is None else f"_vs_{Path(cfg.adversary).name}"
    out = Path(cfg.out) if cfg.out else Path(cfg.learner) / f"eval{suffix}.json"
    check_writable(out, "out")
    overrides = {k: v for k, v in OmegaConf.to_container(cfg.eval).items() if v is not None}
    report = cross_evaluate(cfg.learner, cfg.adversary, overrides, cfg.device)
    write_text_atomically(out, json.dumps(report, indent=2) + "\n")
    print(format_table(report))
    print(f"written: {out}")


def check_writable(path: Path, key: str) -> None:
    """Refuse an output file that cannot be written, before the work that fills it: its folder
    is tried by creating and removing a hidden file there (the report is written atomically,
    through such a sibling)."""
    from armeta_rl.errors import ConfigError
    from armeta_rl.trainers.run_dir import unwritable

    if path.is_dir():
        raise ConfigError(key, str(path), "is a directory, not a file")
    parent = path.parent
    if not parent.is_dir():
        raise ConfigError(key, str(path), f"cannot be written: {parent} is not a directory")
    problem = unwritable(parent)
    if problem is not None:
        raise ConfigError(key, str(path), f"cannot be written in {parent} ({problem})")


@_interruptible("armeta-eval")
def evaluate() -> None:
    """``armeta-eval``: score a saved learner on p0 and on a saved adversary."""
    args = sys.argv[1:]
    multirun = "-m" in args or "--multirun" in args  # a sweep's jobs carry their own learner=
    if not multirun and not any(a.startswith("learner=") for a in args):
        _fail(
            "armeta-eval",
            "config key 'learner' is missing: give the run directory to score, "
            "e.g. armeta-eval learner=runs/... adversary=runs/...",
        )
    check_overrides(args, "armeta-eval", "eval")
    main = hydra.main(version_base=None, config_path=str(config_dir()), config_name="eval")
    main(_guarded("armeta-eval", _eval_task))()
