"""The run's logger: CSV (default), wandb, TensorBoard, MLflow or none, from the config's
``logger`` section, all TorchRL loggers (``torchrl.record.loggers``) fed the same keys; and the
pictures a run draws (the adversary's density, its animation) in the backends that take media."""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from torchrl.record.loggers import (
    CSVLogger,
    Logger,
    MLFlowLogger,
    TensorboardLogger,
    WandbLogger,
)

from armeta_rl.config import LoggerConfig
from armeta_rl.errors import ConfigError
from armeta_rl.trainers.run_dir import CSV_LOG_DIR

TENSORBOARD_DIR = "tensorboard"
"""Where ``logger=tensorboard`` writes under the run directory (``tensorboard --logdir``)."""
MLFLOW_DB = "mlflow.db"
"""The MLflow store ``logger=mlflow`` writes in the run directory when given no tracking URI
(``mlflow ui --backend-store-uri sqlite:///<run>/mlflow.db``)."""


@contextmanager
def run_logger(options: LoggerConfig, run_dir: Path, hparams: dict[str, Any] | None = None
               ) -> Iterator[Logger | None]:
    """The run's logger (:func:`make_logger`) for the ``with`` block, closed when it ends: a
    wandb or MLflow run is finished (marked failed if the block raised), TensorBoard's events
    are flushed. A wandb run left open would be handed back by the next ``wandb.init`` in the
    process (wandb's default ``reinit="return_previous"``), so the jobs of an in-process sweep
    would all log into the first job's run; an MLflow run likewise."""
    logger = make_logger(options, run_dir, hparams)
    failed = True
    try:
        yield logger
        failed = False
    finally:
        if isinstance(logger, WandbLogger):
            logger.experiment.finish(exit_code=1 if failed else 0)
        elif isinstance(logger, TensorboardLogger):
            logger.experiment.close()
        elif isinstance(logger, MLFlowLogger):
            import mlflow

            mlflow.end_run("FAILED" if failed else "FINISHED")


def make_logger(options: LoggerConfig, run_dir: Path, hparams: dict[str, Any] | None = None
                ) -> Logger | None:
    """CSV (default), wandb (offline unless ``WANDB_MODE=online``), TensorBoard (event files in
    ``<run>/tensorboard``), MLflow (``logger.tracking_uri``, default a SQLite store in the run
    directory) or none; ``hparams``, the run's config values, are recorded where the backend
    keeps them (wandb's config, MLflow's parameters)."""
    kind = options.kind
    if kind == "none":
        return None
    if kind == "csv":
        return CSVLogger(exp_name=CSV_LOG_DIR, log_dir=str(run_dir))
    if kind == "wandb":
        run_id = "armeta-" + hashlib.sha1(str(run_dir.resolve()).encode()).hexdigest()[:12]
        offline = os.environ.get("WANDB_MODE", "offline") != "online"
        logger = WandbLogger(
            exp_name=run_dir.name,
            offline=offline,
            save_dir=str(run_dir),
            id=run_id,
            project=options.project,
            log_env_packages=False,
        )
        logger.log_hparams(hparams or {})
        return logger
    if kind == "tensorboard":
        _needs("tensorboard", "tensorboard")
        return TensorboardLogger(exp_name=TENSORBOARD_DIR, log_dir=str(run_dir))
    if kind == "mlflow":
        _needs("mlflow", "mlflow")
        uri = options.tracking_uri or f"sqlite:///{(run_dir / MLFLOW_DB).resolve()}"
        with _quiet("mlflow", "alembic"):  # a new store's table creation, line by line
            logger = MLFlowLogger(exp_name=options.project or run_dir.name, tracking_uri=uri,
                                  artifact_location=(run_dir / "mlflow").resolve().as_uri())
        logger.log_hparams(_flat(hparams or {}))
        return logger
    raise ConfigError("logger.kind", kind, "allowed: csv, wandb, tensorboard, mlflow, none")


def log_picture(logger: Logger | None, key: str, path: Path, step: int | None = None) -> None:
    """The PNG at ``path`` under ``key`` at ``step`` (``None``: the backend's next) where the
    backend shows pictures: a wandb image, a TensorBoard image, an MLflow artifact (under
    ``key``'s folder); CSV takes none."""
    if isinstance(logger, WandbLogger):
        import wandb

        image = {key: wandb.Image(str(path))}
        if step is None:
            logger.experiment.log(image)
        else:
            logger.log_metrics(image, step)
    elif isinstance(logger, TensorboardLogger):
        from matplotlib.image import imread

        logger.experiment.add_image(key, imread(path)[..., :3], step, dataformats="HWC")
    elif isinstance(logger, MLFlowLogger):
        import mlflow

        mlflow.log_artifact(str(path), key)


def log_animation(logger: Logger | None, key: str, path: Path, step: int) -> None:
    """The GIF at ``path`` under ``key``: a wandb video, an MLflow artifact; TensorBoard shows no
    GIF (its frames are its images) and CSV takes none."""
    if isinstance(logger, WandbLogger):
        import wandb

        logger.log_metrics({key: wandb.Video(str(path), format="gif")}, step)
    elif isinstance(logger, MLFlowLogger):
        import mlflow

        mlflow.log_artifact(str(path), key)


@contextmanager
def _quiet(*names: str) -> Iterator[None]:
    """The loggers ``names`` at WARNING for the block, then as they were."""
    loggers = [logging.getLogger(name) for name in names]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)


def _needs(module: str, extra: str) -> None:
    """A :class:`ConfigError` naming the extra that provides ``module`` when it is missing."""
    try:
        __import__(module)
    except ImportError:
        raise ConfigError("logger.kind", extra, f"{module} is not installed: pip install "
                          f"'armeta-rl[{extra}]'") from None


def _flat(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` as ``{"a.b": 1}``: MLflow's parameters are flat."""
    flat = {}
    for key, value in values.items():
        if isinstance(value, dict):
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat
