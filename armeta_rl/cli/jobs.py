"""The one door into a run: :func:`make_job` turns a command line's, a ``-m`` sweep job's or a
Python caller's overrides (a resume directory among them) into a :class:`~armeta_rl.job.Job`, and
:func:`train_task` trains one under the stop signals."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from armeta_rl.cli.compose import (
    checked,
    compose_job,
    config_dir,
    is_hydra_key,
    job_key,
    parse_override,
)
from armeta_rl.cli.failures import Refused
from armeta_rl.config_files import config_files

if TYPE_CHECKING:
    from armeta_rl.config import TrainConfig
    from armeta_rl.job import Job
    from armeta_rl.trainers.run_dir import HeldRunDir


RESUMABLE = ("trainer.iterations", "trainer.stop_at", "device")
"""The keys a resumed run may change that change what it computes: train longer, stop earlier,
continue on another device (its checkpoint loads there)."""


NO_RESULT_KEYS = ("logger", "logger.kind", "logger.project", "logger.tracking_uri",
                  "trainer.progress", "trainer.log_every", "trainer.checkpoint_every",
                  "trainer.density_every", "trainer.keep_freed_memory", "trainer.stop_signals",
                  "adopt")
"""The keys a resumed run may change that change no result (``eval.json`` and every logged
value stay those of the uninterrupted run): where and how often it logs, checkpoints and draws,
the progress bar, the allocator, the stop signals and ``adopt`` (taking checkpoints that record
no run as the run's own). Not ``threads``: torch's reductions split by thread count, so on some
CPUs two threads change a sinusoid AR-MAML run's losses in their eighth digit."""


def make_job(overrides: Sequence[str], composed: DictConfig | None = None,
             run_dir: Path | None = None) -> Job:
    """The one door into a run: the :class:`~armeta_rl.job.Job` of a command line's, a sweep
    job's or a Python caller's ``overrides``.

    With ``resume=<dir>`` among them (or in ``composed``), the run saved there continues: its
    saved config, read once, with the changes a resume may make (:func:`resumed`), in that
    directory. Otherwise ``composed`` (the config composed for ``overrides``; composed here when
    not given) is validated and its method's names checked
    (:func:`~armeta_rl.cli.compose.checked`), for a run in ``run_dir``.

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
    if run_dir is None:
        raise TypeError("a new run's job needs its run_dir")
    if composed is None:
        from hydra import initialize_config_dir

        with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
            composed = compose_job(list(overrides))
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
        override = parse_override(arg)
        name = override.key_or_group
        if name == "resume" or is_hydra_key(name):
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


def train_task(job: Job, held: HeldRunDir | None = None) -> None:
    """Train (or resume) ``job``, stopping cleanly on ``trainer.stop_signals`` and SIGINT
    (:mod:`armeta_rl.preemption`): the signal becomes the process's stop request, which the game
    loop reads. The keys a resume changed (:attr:`Job.taken`) are said first. ``held``: its run
    directory as the CLI checked and locked it (a ``-m`` job's run checks and locks its own)."""
    from armeta_rl.allocator import keep_freed_memory
    from armeta_rl.preemption import listening, refuse_if_asked
    from armeta_rl.trainers.training import run_training

    if job.taken:
        print(f"resuming {job.run_dir} with {', '.join(job.taken)} (they change no result)")
    refuse_if_asked("the same command starts it")
    trainer = job.config.trainer
    if trainer.keep_freed_memory:
        keep_freed_memory()
    with listening(trainer.stop_signals) as stop:
        run_training(job, stop=stop, held=held)


def sweep_task(checked_here: dict[tuple[tuple[str, str], ...], TrainConfig]
               ) -> Callable[[DictConfig], None]:
    """The task of every job of a ``-m`` sweep: the job (:func:`make_job`) of the config Hydra
    composed for it, in the directory Hydra gave it, trained (:func:`train_task`). A job whose
    config this process validated before Hydra started (``checked_here``, by its overrides,
    :func:`~armeta_rl.cli.compose.job_key`: a basic sweep's) and that runs in this process takes
    that config; a job a launcher runs in another process (joblib, Ray, Slurm) validates its
    own, on its machine, as does a ``run_list`` sweep's (``armeta-reproduce`` checked its runs
    before launching)."""
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
            train_task(Job(config, run_dir))
        else:
            train_task(make_job(overrides, cfg, run_dir))

    return task
