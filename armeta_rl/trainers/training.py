"""A training run end to end: build, (resume,) train, evaluate, write the run directory."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.record.loggers import Logger, WandbLogger

from armeta_rl.compiling import COMPILE_KEYS
from armeta_rl.config import CONFIG_FILE, TrainConfig, load_run_config, validate
from armeta_rl.errors import CollectionFailed, ConfigError, RunDirectoryError, TrainingDiverged
from armeta_rl.trainers.checkpoint import RunCheckpoint, newest_intact
from armeta_rl.trainers.density import DensityFrames
from armeta_rl.trainers.evaluation import format_table
from armeta_rl.trainers.game import GameTrainer
from armeta_rl.trainers.loggers import make_logger
from armeta_rl.trainers.players import Players, build_players, load_frozen_leader
from armeta_rl.trainers.report import EVAL_FILE, eval_scalars, evaluate_players
from armeta_rl.trainers.run_dir import (
    CSV_LOG_DIR,
    check_run_dir,
    drop_csv_rows_after,
    run_lock,
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


def run_training(cfg: DictConfig, run_dir: str | Path, progress: bool = True) -> dict | None:
    """Train ``cfg`` in ``run_dir`` (resuming from its checkpoint if ``cfg.resume`` is set),
    holding the run directory's lock throughout.

    Returns the evaluation report, or ``None`` when the run stopped early at ``trainer.stop_at``.

    Raises:
        ConfigError: a bad value, a run directory that cannot be written or that another run
            holds, or (on resume) no intact checkpoint.
        TrainingDiverged: the losses left ``trainer.max_loss``; names the checkpoint kept.
        RunDirectoryError: a checkpoint, log or report could not be written (e.g. a full disk);
            names the checkpoint kept.
    """
    run_dir = Path(run_dir)
    key = "resume" if cfg.resume else "hydra.run.dir"
    config = validate(cfg)
    say(f"run directory: {run_dir}")
    check_run_dir(run_dir, key)
    with run_lock(run_dir, key):
        try:
            return _train_locked(cfg, config, run_dir, progress)
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


def _train_locked(cfg: DictConfig, config: TrainConfig, run_dir: Path, progress: bool
                  ) -> dict | None:
    """:func:`run_training` inside the run directory's lock; ``config`` is ``cfg`` validated."""
    torch.set_num_threads(config.threads)
    players = build_players(config)
    checkpoint = RunCheckpoint(run_dir / "checkpoints", players.leader, players.principle,
                               device=players.device)
    trainer_options = config.trainer
    if trainer_options.frozen_leader is not None and not (
        config.resume and checkpoint.checkpoints()
    ):
        load_frozen_leader(cfg, players)
    start = _open_run(cfg, run_dir, checkpoint)
    logger = make_logger(cfg, run_dir)
    compiled = [key for key in COMPILE_KEYS if OmegaConf.select(cfg, key, default=False)]
    if compiled:
        say(f"{', '.join(compiled)}: the first iterations wait for torch.compile "
            "(about 2 minutes with an empty compile cache)")
    log.info("%s on %s from iteration %d to %d, device %s", config.method.name,
             config.benchmark.name, start, trainer_options.iterations, players.device)
    frames = None
    if players.adversary is not None and trainer_options.density_every > 0:
        frames = DensityFrames(players.adversary, players.initial, run_dir,
                               trainer_options.density_every, logger)
        if start == 0:
            frames.draw(0)  # p_φ = p0
    trainer = GameTrainer(
        players.leader,
        players.principle,
        iterations=trainer_options.iterations,
        meta_batch=trainer_options.meta_batch,
        log_every=trainer_options.log_every,
        checkpoint=checkpoint,
        checkpoint_every=trainer_options.checkpoint_every,
        log=lambda scalars, step: _log_scalars(logger, scalars, step),
        progress=progress and trainer_options.progress,
        max_loss=trainer_options.max_loss,
        after_iteration=frames,
        train_leader=trainer_options.frozen_leader is None,
    )
    trainer.iteration = start
    if trainer.run(stop_at=trainer_options.stop_at) < trainer_options.iterations:
        say(f"stopped at iteration {trainer.iteration}; continue with: "
            f"armeta-train resume={run_dir}")
        return None
    report = _write_report(config, run_dir, players, logger)
    if frames is not None:
        frames.finish(trainer.iteration)
    if logger is not None:
        logger.log_metrics(eval_scalars(report), trainer_options.iterations)
    return report


def _log_scalars(logger: Logger | None, scalars: dict[str, Any], step: int) -> None:
    """An iteration's scalars to the run's logger (CSV, wandb) and a line of the job log."""
    if logger is not None:
        logger.log_metrics(scalars, step)
    log.info("iteration %d: %s", step, " ".join(f"{k}={v:.6g}" for k, v in scalars.items()))


def _open_run(cfg: DictConfig, run_dir: Path, checkpoint: RunCheckpoint) -> int:
    """Clear what a crash left half-written in ``run_dir``, then restore its checkpoint (resume)
    or save the config of a fresh run; returns the iteration training starts from."""
    checkpoint.clean_staging()
    staged = [*run_dir.glob(f".{CONFIG_FILE}.*"), *run_dir.glob(f".{EVAL_FILE}.*"),
              *(run_dir / CSV_LOG_DIR).rglob(".*.csv.*")]
    for path in staged:  # what write_text_atomically left when a crash interrupted it
        path.unlink()
    start = 0
    if cfg.resume:
        if checkpoint.checkpoints():
            start = checkpoint.restore("resume")
        drop_csv_rows_after(run_dir, start)
        saved = load_run_config(run_dir, "resume")
        if saved.trainer.iterations != cfg.trainer.iterations:  # resumed to train longer
            saved.trainer.iterations = cfg.trainer.iterations
            write_config(saved, run_dir / CONFIG_FILE)
    else:
        if checkpoint.checkpoints() or (run_dir / CONFIG_FILE).exists():
            raise ConfigError(
                "hydra.run.dir", str(run_dir),
                "already holds a run: continue it with resume=<dir>, or train into a new "
                "directory",
            )
        write_config(cfg, run_dir / CONFIG_FILE)
    return start


def _write_report(config: TrainConfig, run_dir: Path, players: Players,
                  logger: Logger | None) -> dict:
    """Evaluate the trained players into ``eval.json``, print its table and draw the final p_φ;
    returns the report."""
    report = evaluate_players(config, players)
    write_text_atomically(run_dir / EVAL_FILE, json.dumps(report, indent=2) + "\n")
    say(format_table(report))
    if players.adversary is not None:
        _save_density(players, run_dir / DENSITY_FILE, logger)
    return report


def _save_density(players: Players, path: Path, logger: Logger | None) -> None:
    from armeta_rl.plots import plot_density

    plot_density(players.adversary, players.initial, path)
    if isinstance(logger, WandbLogger):
        import wandb

        logger.experiment.log({"adversary/density": wandb.Image(str(path))})
