"""The run's logger: CSV (default), wandb or none, from the config's ``logger`` section."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from torchrl.record.loggers import CSVLogger, Logger, WandbLogger

from armeta_rl.config import LoggerConfig
from armeta_rl.errors import ConfigError
from armeta_rl.trainers.run_dir import CSV_LOG_DIR


@contextmanager
def run_logger(options: LoggerConfig, run_dir: Path, hparams: dict[str, Any] | None = None
               ) -> Iterator[Logger | None]:
    """The run's logger (:func:`make_logger`) for the ``with`` block; a wandb run is finished
    when the block ends (marked failed if it raised). A wandb run left open would be handed back
    by the next ``wandb.init`` in the process (wandb's default ``reinit="return_previous"``), so
    the jobs of an in-process sweep would all log into the first job's run."""
    logger = make_logger(options, run_dir, hparams)
    failed = True
    try:
        yield logger
        failed = False
    finally:
        if isinstance(logger, WandbLogger):
            logger.experiment.finish(exit_code=1 if failed else 0)


def make_logger(options: LoggerConfig, run_dir: Path, hparams: dict[str, Any] | None = None
                ) -> Logger | None:
    """CSV (default), wandb (offline unless ``WANDB_MODE=online``; ``hparams``, the run's config
    values, recorded as its config) or none."""
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
    raise ConfigError("logger.kind", kind, "allowed: csv, wandb, none")
