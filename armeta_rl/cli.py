"""Console entry points ``armeta-train`` and ``armeta-eval`` (Hydra).

Bad input ends with one line naming the config key, the value and what is allowed, and exit
code 2. Group choices (``benchmark=``, ``method=``, ``logger=``) are checked before Hydra starts,
values before any training work.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

import hydra
from omegaconf import DictConfig, OmegaConf

from armeta_rl.allocator import keep_freed_memory

GROUPS = ("benchmark", "method", "logger")


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


def check_group_choices(args: list[str], prog: str) -> None:
    """Reject an unknown ``benchmark=``/``method=``/``logger=`` (also in ``-m`` comma sweeps)."""
    for arg in args:
        key, sep, value = arg.lstrip("+~").partition("=")
        if not sep or key not in GROUPS or "(" in value:
            continue
        allowed = group_choices(key)
        for choice in value.split(","):
            if choice not in allowed:
                _fail(prog, f"config key '{key}' = {choice!r}: allowed: {', '.join(allowed)}")


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
    check_group_choices(args, "armeta-train")
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
    if not any(a.startswith("learner=") for a in args):
        _fail(
            "armeta-eval",
            "config key 'learner' is missing: give the run directory to score, "
            "e.g. armeta-eval learner=runs/... adversary=runs/...",
        )
    main = hydra.main(version_base=None, config_path=str(config_dir()), config_name="eval")
    main(_guarded("armeta-eval", _eval_task))()
