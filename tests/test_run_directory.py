"""The run directory across crashes: a resumed run's CSV logs equal an uninterrupted run's, and a
fresh run never writes into another run's checkpoints."""

from __future__ import annotations

import shutil

import pytest

from armeta_rl.cli.jobs import make_job
from armeta_rl.errors import ConfigError
from armeta_rl.job import Job
from armeta_rl.trainers.run_dir import CSV_LOG_DIR
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, train_config

CSV_RUN = (*SMALL_RUN, "method=ar_maml", "logger=csv", "trainer.log_every=1",
           "trainer.checkpoint_every=2")


def csv_logs(run_dir):
    """``{metric: rows}`` of a run's CSV logs, without wall-clock timings."""
    scalars = run_dir / CSV_LOG_DIR / "scalars"
    return {
        str(path.relative_to(scalars)): path.read_text().splitlines()
        for path in sorted(scalars.rglob("*.csv"))
        if not str(path.relative_to(scalars)).startswith("time")
    }


def test_a_run_resumed_after_a_crash_logs_every_iteration_once(tmp_path):
    run_training(Job(train_config(*CSV_RUN), tmp_path / "whole"), progress=False)
    crashed = tmp_path / "crashed"
    run_training(Job(train_config(*CSV_RUN, "trainer.stop_at=3"), crashed), progress=False)
    # the crash: iteration 3 was logged, but its checkpoint never reached the disk
    newest = max((crashed / "checkpoints").iterdir())
    assert newest.name.endswith("3")
    shutil.rmtree(newest)
    assert max(int(row.split(",")[0]) for row in csv_logs(crashed)["train/leader_loss.csv"]) == 3

    run_training(make_job([f"resume={crashed}"]), progress=False)
    whole, resumed = csv_logs(tmp_path / "whole"), csv_logs(crashed)
    steps = [int(row.split(",")[0]) for row in whole["train/leader_loss.csv"]]
    assert steps == list(range(1, 7))
    assert resumed == whole


def test_a_fresh_run_refuses_a_directory_holding_checkpoints(tmp_path):
    run_training(Job(train_config(*SMALL_RUN), tmp_path), progress=False)
    with pytest.raises(ConfigError, match=r"hydra\.run\.dir.*resume="):
        run_training(Job(train_config(*SMALL_RUN), tmp_path), progress=False)
