"""The run's logger: CSV (default), wandb or none, from ``cfg.logger``."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from torchrl.record.loggers import CSVLogger, Logger, WandbLogger

from armeta_rl.errors import ConfigError
from armeta_rl.trainers.run_dir import CSV_LOG_DIR


def make_logger(cfg: DictConfig, run_dir: Path) -> Logger | None:
    """CSV (default), wandb (offline unless ``WANDB_MODE=online``) or none."""
    kind = cfg.logger.kind
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
            project=cfg.logger.project,
            log_env_packages=False,
        )
        logger.log_hparams(OmegaConf.to_container(cfg, resolve=True))
        return logger
    raise ConfigError("logger.kind", kind, "allowed: csv, wandb, none")
