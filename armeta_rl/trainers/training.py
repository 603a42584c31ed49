"""A training run end to end: build, (resume,) train, evaluate, write the run directory."""

from __future__ import annotations

import json
import logging
import signal
import textwrap
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from torchrl.record.loggers import Logger

from armeta_rl.compiling import COMPILE_KEYS
from armeta_rl.config import CONFIG_FILE, TrainConfig, value_at
from armeta_rl.errors import (
    CollectionFailed,
    ConfigError,
    RunDirectoryError,
    RunStopped,
    TrainingDiverged,
)
from armeta_rl.job import Job
from armeta_rl.preemption import EXIT_INTERRUPTED, StopRequest
from armeta_rl.trainers.checkpoint import (
    RunCheckpoint,
    newest_intact,
    run_identity,
    saved_identity,
)
from armeta_rl.trainers.density import FRAMES_DIR, PICTURE_KEY, DensityFrames, readable
from armeta_rl.trainers.evaluation import ReportInvalid, curve_steps, format_table, read_report
from armeta_rl.trainers.game import GameTrainer
from armeta_rl.trainers.loggers import log_picture, run_logger
from armeta_rl.trainers.players import Players, build_players, load_frozen_leader
from armeta_rl.trainers.report import EVAL_FILE, eval_scalars, evaluate_players
from armeta_rl.trainers.run_dir import (
    CSV_LOG_DIR,
    HeldRunDir,
    drop_csv_rows_after,
    hold_run_dir,
    staged_leftovers,
    write_atomically,
    write_config,
    write_text_atomically,
)

DENSITY_FILE = "density.png"
log = logging.getLogger(__name__)
"""The job log: under ``armeta-train``, ``<run dir>/armeta-train.log``
(``configs/hydra/job_logging/run_log.yaml``)."""


def say(message: str) -> None:
    """Print ``message`` and write it to the job log."""
    print(message)
    log.info(message)


def run_training(job: Job, progress: bool = True, stop: StopRequest | None = None,
                 held: HeldRunDir | None = None) -> dict | None:
    """Train ``job``'s config in its run directory (resuming from its checkpoint if
    ``config.resume`` is set: the job holds the config the run saved, so nothing is read back
    here), holding the run directory's lock throughout; a resumed run that has finished (its
    ``eval.json`` passes its schema) is left as it is.

    ``held``: the run directory as the caller already checked and locked it
    (:func:`~armeta_rl.trainers.run_dir.hold_run_dir`: the CLI does, before Hydra writes there);
    without it, the run checks and locks its directory itself.

    ``stop`` is checked after every iteration (the CLI sets it on a preemption signal,
    :mod:`armeta_rl.preemption`): once it is requested, the run checkpoints the iteration it
    finished and stops; one requested during the final evaluation lets the run finish, and the
    run says so.

    Returns the evaluation report, or ``None`` when the run stopped early at ``trainer.stop_at``.

    Raises:
        ConfigError: a value the built players refuse, a run directory that cannot be written
            or that another run holds, or (on resume) no intact checkpoint.
        TrainingDiverged: the losses left ``trainer.max_loss``; names the checkpoint kept.
        RunDirectoryError: a checkpoint, log or report could not be written (e.g. a full disk);
            names the checkpoint kept.
        RunStopped: ``stop`` was requested before the run finished; names the checkpoint kept
            and the resume command.
    """
    run_dir = job.run_dir
    if held is None:
        key = "resume" if job.config.resume else "hydra.run.dir"
        with hold_run_dir(run_dir, key, resume=job.config.resume is not None) as held:
            return run_training(job, progress, stop, held)
    if held.path != run_dir:
        raise ValueError(f"the run directory held ({held.path}) is not the job's ({run_dir})")
    stop = stop if stop is not None else StopRequest()
    say(f"run directory: {run_dir}")
    try:
        return _train_locked(job, progress, stop)
    except KeyboardInterrupt:
        if stop.signal != signal.SIGINT:  # not the second Ctrl-C of preemption.listening
            raise
        raise RunStopped(_stopped("stopped at once by a second SIGINT", run_dir),
                         EXIT_INTERRUPTED) from None
    except (TrainingDiverged, CollectionFailed, RunDirectoryError, OSError) as error:
        stopped = isinstance(error, (TrainingDiverged, CollectionFailed))
        kind = type(error) if stopped else RunDirectoryError
        if isinstance(error, OSError):  # e.g. a log or eval.json on a full disk
            error = f"cannot write {error.filename or run_dir}: {error.strerror or error}"
        kept = newest_intact(run_dir / "checkpoints")
        raise kind(
            f"{error}; the last good checkpoint {kept.name} is kept: armeta-train "
            f"resume={run_dir} continues from it"
            if kept is not None
            else f"{error}; no checkpoint had been written yet"
        ) from None


def _stopped(reason: str, run_dir: Path, written: Path | None = None) -> str:
    """The line a stopped run ends with: why, the checkpoint it continues from, and how."""
    if written is not None:
        kept = f"checkpoint {written} written"
    else:
        newest = newest_intact(run_dir / "checkpoints")
        kept = (f"the last checkpoint {newest} is kept" if newest is not None
                else "no checkpoint yet (it starts again from iteration 0)")
    return f"{reason}: {kept}; continue with: armeta-train resume={run_dir}"


def finished_report(run_dir: Path) -> dict | None:
    """The run's ``eval.json`` if the run has finished: the file is written last, and only
    counts when it passes its schema (a damaged or hand-edited one is evaluated again)."""
    try:
        return read_report(run_dir / EVAL_FILE)
    except ReportInvalid:
        return None


def _train_locked(job: Job, progress: bool, stop: StopRequest) -> dict | None:
    """:func:`run_training` inside the run directory's lock."""
    config, run_dir = job.config, job.run_dir
    report = finished_report(run_dir) if config.resume else None
    if report is not None and job.saved_iterations == config.trainer.iterations:
        say(f"{run_dir} has finished: nothing to do ({EVAL_FILE} holds its evaluation; "
            "resume with a larger trainer.iterations to train longer)")
        return report
    torch.set_num_threads(config.threads)
    players = build_players(config)
    if config.trainer.follower_rollouts > 1 and not players.leader.on_policy:
        raise ConfigError("trainer.follower_rollouts", config.trainer.follower_rollouts,
                          f"must be 1 on {config.benchmark.name}: its learner scores the "
                          "follower's tasks on the step's own data, not on fresh rollouts")
    label = players.principle.label
    if label != "loss" and not getattr(players.leader.collector, "reports_forward_reward", False):
        section = f"risk.{config.method.risk}.label"
        raise ConfigError(section, "last_step", f"needs an env that reports its forward reward "
                          f"after every step (the locomotion families), not "
                          f"{config.benchmark.name}'s")
    curve_steps(players.leader, config.eval.adaptation_steps)  # refused before training
    values = config.values()
    # a resumed run keeps the identity its config was saved with (keys added since at defaults)
    identity = run_identity(values)
    as_saved = saved_identity(run_dir) if config.resume else None
    checkpoint = RunCheckpoint(run_dir / "checkpoints", players.leader, players.principle,
                               device=players.device, identity=as_saved or identity,
                               adopt=config.adopt, accepts=[identity])
    trainer_options = config.trainer
    if trainer_options.frozen_leader is not None and not (
        config.resume and checkpoint.checkpoints()
    ):
        load_frozen_leader(config, players)
    start = _open_run(config, values, run_dir, checkpoint, job.saved,
                      evaluated=report is not None)
    with run_logger(config.logger, run_dir, values) as logger:
        compiled = [key for key in COMPILE_KEYS if value_at(values, key)]
        if compiled:
            say(f"{', '.join(compiled)}: the first iterations wait for torch.compile "
                "(about 2 minutes with an empty compile cache)")
        log.info("%s on %s from iteration %d to %d, device %s", config.method.name,
                 config.benchmark.name, start, trainer_options.iterations, players.device)
        frames = None
        if players.adversary is not None and trainer_options.density_every > 0:
            frames = DensityFrames(players.adversary, players.initial, run_dir,
                                   trainer_options.density_every, logger)
            if start == 0 or (start % trainer_options.density_every == 0
                               and not readable(frames.frame_path(start))):
                frames.draw(start)  # p0; or the checkpoint's p_φ, whose frame a kill cut off
        options = trainer_options if progress else replace(trainer_options, progress=False)
        trainer = GameTrainer(players.leader, players.principle, options,
                              log=lambda scalars, step: _log_scalars(logger, scalars, step),
                              checkpoint=checkpoint, after_iteration=frames,
                              label=run_dir.name)
        trainer.iteration = start
        reached = trainer.run(stop=stop)
        planned = min(trainer_options.iterations,
                      trainer_options.stop_at or trainer_options.iterations)
        if stop.requested and reached < planned:
            written = checkpoint.path(reached) if reached > start else None
            raise RunStopped(_stopped(f"stopped by {stop.name} after iteration {reached}", run_dir,
                                      written), stop.exit_code)
        if reached < trainer_options.iterations:
            say(f"stopped at iteration {trainer.iteration}; continue with: "
                f"armeta-train resume={run_dir}")
            return None
        report = _finish(config, run_dir, players, logger, frames, reached, checkpoint.identity)
        if stop.requested:  # it came after the last checkpoint: finishing was the quicker way
            say(f"{stop.name} arrived during the final evaluation: the run finished first "
                f"({EVAL_FILE} written)")
        return report


def _log_scalars(logger: Logger | None, scalars: dict[str, Any], step: int) -> None:
    """An iteration's scalars to the run's logger (CSV, wandb) and a line of the job log."""
    if logger is not None:
        logger.log_metrics(scalars, step)
    log.info("iteration %d: %s", step, " ".join(f"{k}={v:.6g}" for k, v in scalars.items()))


def _open_run(config: TrainConfig, values: dict[str, Any], run_dir: Path,
              checkpoint: RunCheckpoint, saved: dict[str, Any] | None,
              evaluated: bool = False) -> int:
    """Clear what a crash left half-written in ``run_dir``, then restore its checkpoint (resume)
    or save the config of a fresh run (``values``: :meth:`TrainConfig.values`); returns the
    iteration training starts from. ``saved``: the resumed run's saved config (:class:`Job`),
    written back with the new ``trainer.iterations`` when it trains longer. ``evaluated``: the
    run's ``eval.json`` holds the evaluation at the iteration it resumes from (a finished run
    resumed to train longer)."""
    if checkpoint.directory.exists() and not checkpoint.directory.is_dir():
        raise ConfigError("resume" if config.resume else "hydra.run.dir", str(run_dir),
                          f"its {checkpoint.directory.name} is not a directory: move it away")
    checkpoint.clean_staging()
    for path in staged_leftovers(run_dir, (".", CSV_LOG_DIR, FRAMES_DIR)):
        path.unlink()  # what an atomic write left when a crash interrupted it
    start = 0
    if config.resume:
        if checkpoint.checkpoints() or checkpoint.set_aside():
            start = checkpoint.restore("resume")
        drop_csv_rows_after(run_dir, start, evaluated)
        if saved["trainer"]["iterations"] != config.trainer.iterations:  # to train longer
            longer = {**saved, "trainer": {**saved["trainer"],
                                           "iterations": config.trainer.iterations}}
            write_config(longer, run_dir / CONFIG_FILE)
            (run_dir / EVAL_FILE).unlink(missing_ok=True)  # the run is no longer finished
    else:
        if checkpoint.checkpoints() or (run_dir / CONFIG_FILE).exists():
            raise ConfigError(
                "hydra.run.dir", str(run_dir),
                "already holds a run: continue it with resume=<dir>, or train into a new "
                "directory",
            )
        write_config(values, run_dir / CONFIG_FILE)
    return start


def _finish(config: TrainConfig, run_dir: Path, players: Players, logger: Logger | None,
            frames: DensityFrames | None, iteration: int, identity: dict) -> dict:
    """Evaluate the trained players, log the scores, draw the final p_φ and its animation, and
    write ``eval.json`` last (atomically): a run with an ``eval.json`` has everything. Prints the
    table; returns the report."""
    report = {**evaluate_players(config, players), "config_sha256": identity["config_sha256"]}
    if logger is not None:
        logger.log_metrics(eval_scalars(report), config.trainer.iterations)
    if players.adversary is not None:
        _save_density(players, run_dir / DENSITY_FILE, logger, iteration)
    if frames is not None:
        frames.finish(iteration)
    write_text_atomically(run_dir / EVAL_FILE, json.dumps(report, indent=2) + "\n")
    say(end_of_run(config, run_dir, report, players.adversary is not None))
    return report


TABLE_LEGEND = ("R: rollouts per task, a task's score their mean; ± one standard error over "
                "tasks; cvar_α: the mean over the worst 1 − α of tasks; gain: after adaptation − "
                "before ('not adapting': within two standard errors of 0)")
"""What the end-of-run table's columns are, said once under it."""


def end_of_run(config: TrainConfig, run_dir: Path, report: dict, drew: bool) -> str:
    """What a finished run prints: its name, the table (with its adaptation curve), what the
    columns are, and where the run directory, the report and the density picture (``drew``) are;
    a ``-m`` sweep's jobs each print theirs under their own run's name."""
    pictures = (f"; the adversary's density (p_φ against p0): {run_dir / DENSITY_FILE}, "
                "density.gif" if drew else "")
    return "\n".join([
        f"{run_dir.name}: {config.method.name} on {config.benchmark.name}, seed {config.seed}",
        format_table(report), textwrap.fill(TABLE_LEGEND, 100),
        f"run directory: {run_dir} (report: {EVAL_FILE}{pictures})"])


def _save_density(players: Players, path: Path, logger: Logger | None, iteration: int) -> None:
    from armeta_rl.plots import plot_density

    title = f"p_φ after {iteration} meta-iterations"
    write_atomically(path, lambda staged: plot_density(players.adversary, players.initial,
                                                       staged, title=title))
    log_picture(logger, PICTURE_KEY, path)
