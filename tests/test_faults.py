"""Fault injection: runs killed at random points, checkpoint files truncated or garbled, a full
disk, concurrent starts. Each case asserts that nothing is lost: the run resumes to exactly the
uninterrupted run's evaluation and logs, or it is refused with a clear error."""

from __future__ import annotations

import errno
import json
import logging
import os
import random
import shutil
import subprocess
import sys
import time

import pytest
from conftest import SMALL_RUN, compose_train

import armeta_rl.trainers.checkpoint as checkpoint_module
from armeta_rl.cli import _guarded
from armeta_rl.errors import CheckpointBroken, ConfigError, RunDirectoryError, TrainingDiverged
from armeta_rl.trainers import game
from armeta_rl.trainers.checkpoint import MANIFEST, verify
from armeta_rl.trainers.run import CSV_LOG_DIR, EVAL_FILE, cross_evaluate, run_training
from armeta_rl.trainers.runs import LOCK_FILE

RUN = (*SMALL_RUN, "method=ar_maml", "trainer.meta_batch=5", "logger=csv",
       "trainer.log_every=1", "trainer.checkpoint_every=2")
"""A six-iteration AR-MAML run with checkpoints at 2, 4 and 6 (two kept) and CSV logs."""

KILLS = 20


class Killed(BaseException):
    """Raised at an injected fault point: like SIGKILL, no ``except Exception`` handles it."""


def outcome(run_dir):
    """What a finished run leaves: its evaluation and its CSV logs (without wall-clock times)."""
    scalars = run_dir / CSV_LOG_DIR / "scalars"
    logs = {
        str(path.relative_to(scalars)): path.read_text()
        for path in sorted(scalars.rglob("*.csv"))
        if not str(path.relative_to(scalars)).startswith("time")
    }
    return json.loads((run_dir / EVAL_FILE).read_text()), logs


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """The uninterrupted run."""
    run_dir = tmp_path_factory.mktemp("whole")
    run_training(compose_train(*RUN), run_dir, progress=False)
    return run_dir


def finish(run_dir):
    """Continue ``run_dir`` after a fault: resume it, or start it afresh when the fault came
    before its config was saved (then nothing of it was kept)."""
    if (run_dir / "config.yaml").exists():
        run_training(compose_train(*RUN, f"resume={run_dir}"), run_dir, progress=False)
    else:
        run_training(compose_train(*RUN), run_dir, progress=False)


class FaultPoints:
    """Counts calls of the run's write and step operations and raises :class:`Killed` just before
    the ``kill_at``-th (never, for ``None``)."""

    def __init__(self, monkeypatch, kill_at):
        self.calls, self.kill_at = 0, kill_at
        for owner, name in ((checkpoint_module, "write_file"), (checkpoint_module, "seal"),
                            (os, "replace"), (game.GameTrainer, "train_iteration")):
            monkeypatch.setattr(owner, name, self.wrap(getattr(owner, name)))

    def wrap(self, function):
        def faulty(*args, **kwargs):
            self.calls += 1
            if self.calls == self.kill_at:
                raise Killed
            return function(*args, **kwargs)

        return faulty


def test_a_run_killed_at_random_points_resumes_exactly(tmp_path, whole, monkeypatch):
    with monkeypatch.context() as patch:
        counter = FaultPoints(patch, None)
        run_training(compose_train(*RUN), tmp_path / "counted", progress=False)
    points = counter.calls
    kill_points = random.Random(29).sample(range(1, points + 1), KILLS)
    expected = outcome(whole)
    for kill_at in kill_points:
        run_dir = tmp_path / f"killed_at_{kill_at}"
        with monkeypatch.context() as patch:
            FaultPoints(patch, kill_at)
            with pytest.raises(Killed):
                run_training(compose_train(*RUN), run_dir, progress=False)
        finish(run_dir)
        assert outcome(run_dir) == expected, f"killed at fault point {kill_at} of {points}"
        assert not [p for p in (run_dir / "checkpoints").iterdir() if p.name.startswith(".")]


def test_a_run_killed_by_sigkill_resumes_exactly(tmp_path, whole):
    """A real SIGKILL (no cleanup runs) right after the first checkpoint appears."""
    run_dir = tmp_path / "run"
    cli = [sys.executable, "-c", "from armeta_rl.cli import train; train()"]
    process = subprocess.Popen([*cli, *RUN, f"hydra.run.dir={run_dir}"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not list(run_dir.glob("checkpoints/*")) and process.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    process.kill()
    process.wait()
    finish(run_dir)
    assert outcome(run_dir) == outcome(whole)


def corrupt(path, how):
    data = path.read_bytes()
    if how == "empty":
        path.write_bytes(b"")
    elif how == "half":
        path.write_bytes(data[: len(data) // 2])
    else:  # garbled: same size, bytes flipped in the middle
        middle = len(data) // 2
        path.write_bytes(data[:middle] + bytes(b ^ 0xFF for b in data[middle:middle + 8])
                         + data[middle + 8:])


FILES = {
    "manifest": MANIFEST,
    "leader": "components/0000-leader/state.pt",
    "principle": "components/0001-principle/state.pt",
    "progress": "components/0002-progress/value.json",
    "rng": "components/0003-rng/state.pt",
}


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """A run stopped at iteration 4 (checkpoints 2 and 4)."""
    run_dir = tmp_path_factory.mktemp("stopped")
    run_training(compose_train(*RUN, "trainer.stop_at=4"), run_dir, progress=False)
    return run_dir


@pytest.mark.parametrize("how", ["empty", "half", "garbled"])
@pytest.mark.parametrize("kind", sorted(FILES))
def test_a_broken_newest_checkpoint_falls_back_to_the_intact_one(
    tmp_path, whole, stopped, kind, how, caplog
):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    newest = run_dir / "checkpoints" / "checkpoint-000000000004"
    corrupt(newest / FILES[kind], how)
    assert verify(newest) is not None
    with pytest.raises(CheckpointBroken, match="checkpoint-000000000004 is broken"):
        cross_evaluate(run_dir, None)
    with caplog.at_level(logging.WARNING):
        finish(run_dir)
    assert "checkpoint-000000000004 is broken" in caplog.text
    assert outcome(run_dir) == outcome(whole)


def test_a_missing_components_directory_falls_back(tmp_path, whole, stopped, caplog):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    shutil.rmtree(run_dir / "checkpoints" / "checkpoint-000000000004" / "components")
    with caplog.at_level(logging.WARNING):
        finish(run_dir)
    assert "missing components/" in caplog.text
    assert outcome(run_dir) == outcome(whole)


def test_no_intact_checkpoint_is_a_clear_refusal(tmp_path, stopped):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    for checkpoint in (run_dir / "checkpoints").iterdir():
        corrupt(checkpoint / FILES["leader"], "garbled")
    with pytest.raises(CheckpointBroken, match="has no intact checkpoint; broken: checkpoint-0"):
        finish(run_dir)


def enospc_from(monkeypatch, call):
    """Make the checkpoint writer fail with a full disk from its ``call``-th call on."""
    write_file, calls = checkpoint_module.write_file, [0]

    def full_disk(path, data):
        calls[0] += 1
        if calls[0] >= call:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        write_file(path, data)

    monkeypatch.setattr(checkpoint_module, "write_file", full_disk)


def test_a_full_disk_keeps_the_last_intact_checkpoint_and_resumes_exactly(
    tmp_path, whole, monkeypatch, capsys
):
    run_dir = tmp_path / "run"
    with monkeypatch.context() as patch:
        enospc_from(patch, 5)  # the second checkpoint (iteration 4): 4 files per checkpoint
        task = _guarded("armeta-train", lambda cfg: run_training(cfg, run_dir, progress=False))
        with pytest.raises(SystemExit) as exit_:
            task(compose_train(*RUN))
    assert exit_.value.code == 1
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "No space left on device" in error[0], error
    kept = sorted(p.name for p in (run_dir / "checkpoints").iterdir())
    assert kept == ["checkpoint-000000000002"]
    finish(run_dir)
    assert outcome(run_dir) == outcome(whole)


def test_a_full_disk_error_is_a_run_directory_error(tmp_path, monkeypatch):
    enospc_from(monkeypatch, 1)
    with pytest.raises(RunDirectoryError, match="checkpoint-000000000002: No space left"):
        run_training(compose_train(*RUN), tmp_path, progress=False)


def test_interrupted_staging_is_cleaned(tmp_path, whole, stopped):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    leftover = run_dir / "checkpoints" / ".checkpoint-000000000006.staging-1"
    leftover.mkdir()
    (leftover / "manifest.json").write_text("{")
    finish(run_dir)
    assert not leftover.exists()
    assert outcome(run_dir) == outcome(whole)


HOLD = "import fcntl, os, sys, time; fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT); " \
       "fcntl.flock(fd, fcntl.LOCK_EX); os.write(fd, str(os.getpid()).encode()); " \
       "print('held', flush=True); time.sleep(60)"


def test_a_locked_run_directory_is_refused_until_its_holder_dies(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(tmp_path / LOCK_FILE)],
                              stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(ConfigError, match=rf"in use by another run \(pid {holder.pid}\)"):
        run_training(compose_train(*RUN), tmp_path, progress=False)
    assert not (tmp_path / "config.yaml").exists()
    holder.kill()
    holder.wait()
    run_training(compose_train(*RUN), tmp_path, progress=False)  # the dead holder's lock
    assert (tmp_path / LOCK_FILE).read_text().strip() == str(os.getpid())


def test_two_runs_started_together_into_one_directory(tmp_path, whole):
    cli = [sys.executable, "-c", "from armeta_rl.cli import train; train()"]
    runs = [subprocess.Popen([*cli, *RUN, f"hydra.run.dir={tmp_path}"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(run.wait(timeout=300), run.stderr.read()) for run in runs]
    codes = sorted(code for code, _ in results)
    assert codes == [0, 2], results
    refused = next(err for code, err in results if code == 2).strip().splitlines()
    assert len(refused) == 1 and "in use by another run" in refused[0]
    assert outcome(tmp_path) == outcome(whole)


def test_the_divergence_bound_stops_the_run_and_names_the_checkpoint(tmp_path, monkeypatch):
    with pytest.raises(TrainingDiverged, match="beyond trainer.max_loss = 0.001.*no checkpoint"):
        run_training(compose_train(*RUN, "trainer.max_loss=1e-3"), tmp_path, progress=False)
    run_dir = tmp_path / "later"
    step = game.GameTrainer.train_iteration

    def blows_up_at_3(self):
        """Iteration 3's losses leave a bound that the first two kept."""
        if self.iteration == 2:
            self.max_loss = 1e-3
        return step(self)

    monkeypatch.setattr(game.GameTrainer, "train_iteration", blows_up_at_3)
    with pytest.raises(TrainingDiverged, match="iteration 3.*checkpoint-000000000002 is kept"):
        run_training(compose_train(*RUN), run_dir, progress=False)
