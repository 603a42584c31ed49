"""Console entry points ``armeta-train`` and ``armeta-eval`` (Hydra).

Bad input ends with one line naming the config key, the value and what is allowed, and exit
code 2. Overrides (group choices such as ``benchmark=`` and the keys of the others) are checked
before Hydra starts, values before any training work.
"""

from __future__ import annotations

import difflib
import itertools
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

import hydra
from omegaconf import DictConfig, OmegaConf

from armeta_rl.allocator import keep_freed_memory

GROUPS = ("benchmark", "method", "logger")
_ABSENT = object()


def config_dir() -> Path:
    """The Hydra config directory: packaged in a wheel, or the repository's ``configs/``."""
    packaged = Path(__file__).parent / "configs"
    return packaged if packaged.is_dir() else Path(__file__).resolve().parents[1] / "configs"


def _fail(prog: str, message: str, code: int = 2) -> NoReturn:
    print(f"{prog}: error: {message}", file=sys.stderr)
    sys.exit(code)


def group_choices(group: str) -> list[str]:
    """Names of the configs available for a config group, e.g. the benchmarks."""
    return sorted(path.stem for path in (config_dir() / group).glob("*.yaml"))


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


def _guarded(prog: str, task: Callable[[DictConfig], None]) -> Callable[[DictConfig], None]:
    """Run ``task`` turning the package's user errors into one line and an exit code."""

    def wrapped(cfg: DictConfig) -> None:
        from armeta_rl.errors import ConfigError, TrainingDiverged

        try:
            task(cfg)
        except ConfigError as error:
            _fail(prog, str(error))
        except TrainingDiverged as error:
            _fail(prog, f"training stopped: {error}; the last good checkpoint is kept", code=1)

    return wrapped


def _train_task(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    from armeta_rl.config import check_config, load_run_config

    if cfg.resume:
        saved = load_run_config(cfg.resume, "resume")
        cfg = OmegaConf.merge(
            saved, {"resume": cfg.resume, "trainer": {"stop_at": cfg.trainer.stop_at}}
        )
        run_dir = Path(cfg.resume)
    else:
        run_dir = Path(HydraConfig.get().runtime.output_dir)
    check_config(cfg)
    from armeta_rl.trainers.run import run_training

    run_training(cfg, run_dir)


def train() -> None:
    """``armeta-train``: train a method on a benchmark (see ``configs/train.yaml``)."""
    keep_freed_memory()
    args = sys.argv[1:]
    check_overrides(args, "armeta-train", "train", GROUPS)
    resume = next((a.split("=", 1)[1] for a in args if a.startswith("resume=")), None)
    if resume and not any(a.startswith("hydra.run.dir=") for a in args):
        args += [f"hydra.run.dir={resume}", "hydra.output_subdir=null"]
    sys.argv = [sys.argv[0], *args]
    main = hydra.main(version_base=None, config_path=str(config_dir()), config_name="train")
    main(_guarded("armeta-train", _train_task))()


def _eval_task(cfg: DictConfig) -> None:
    from armeta_rl.trainers.evaluation import format_table
    from armeta_rl.trainers.run import cross_evaluate

    overrides = {k: v for k, v in OmegaConf.to_container(cfg.eval).items() if v is not None}
    report = cross_evaluate(cfg.learner, cfg.adversary, overrides)
    suffix = "" if cfg.adversary is None else f"_vs_{Path(cfg.adversary).name}"
    out = Path(cfg.out) if cfg.out else Path(cfg.learner) / f"eval{suffix}.json"
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(format_table(report))
    print(f"written: {out}")


def evaluate() -> None:
    """``armeta-eval``: score a saved learner on p0 and on a saved adversary."""
    keep_freed_memory()
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
