"""Fault injection: runs killed at random points, checkpoint files truncated or garbled, a full
disk, concurrent starts. Each case asserts that nothing is lost: the run resumes to exactly the
uninterrupted run's evaluation and logs, or it is refused with a clear error."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import logging
import math
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from PIL import Image

import armeta_rl.trainers.checkpoint as checkpoint_module
from armeta_rl.cli import _eval_task, train
from armeta_rl.cli.compose import config_dir
from armeta_rl.cli.failures import OUT_OF_MEMORY, Refused, report_errors
from armeta_rl.cli.jobs import make_job
from armeta_rl.config import load_run_config, validate
from armeta_rl.errors import CheckpointBroken, ConfigError, RunDirectoryError, TrainingDiverged
from armeta_rl.job import Job
from armeta_rl.run_files import FileRefused
from armeta_rl.trainers import game
from armeta_rl.trainers.checkpoint import MANIFEST, verify
from armeta_rl.trainers.players import load_players
from armeta_rl.trainers.report import EVAL_FILE
from armeta_rl.trainers.run_dir import CSV_LOG_DIR, LOCK_FILE
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, compose_train, cross_evaluate, in_process, train_config

RUN = (*SMALL_RUN, "method=ar_maml", "trainer.meta_batch=5", "logger=csv",
       "trainer.log_every=1", "trainer.checkpoint_every=2", "trainer.density_every=0")
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
    run_training(Job(train_config(*RUN), run_dir), progress=False)
    return run_dir


def finish(run_dir):
    """Continue ``run_dir`` after a fault: resume it, or start it afresh when the fault came
    before its config was saved (then nothing of it was kept)."""
    if (run_dir / "config.yaml").exists():
        run_training(make_job([f"resume={run_dir}"]), progress=False)
    else:
        run_training(Job(train_config(*RUN), run_dir), progress=False)


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
        run_training(Job(train_config(*RUN), tmp_path / "counted"), progress=False)
    points = counter.calls
    rng = random.Random(29)
    kill_points = rng.sample(range(1, points + 1), KILLS)
    expected = outcome(whole)
    for n, kill_at in enumerate(kill_points):
        run_dir = tmp_path / f"killed_at_{kill_at}"
        with monkeypatch.context() as patch:
            FaultPoints(patch, kill_at)
            with pytest.raises(Killed):
                run_training(Job(train_config(*RUN), run_dir), progress=False)
        if n % 4 == 0:  # every fourth run is killed again while it resumes
            with monkeypatch.context() as patch:
                again = FaultPoints(patch, rng.randint(1, points // 2))
                with contextlib.suppress(Killed):  # unless its resume had fewer points
                    finish(run_dir)
                assert again.calls >= 1
        finish(run_dir)
        assert outcome(run_dir) == expected, f"killed at fault point {kill_at} of {points}"
        assert not [p for p in (run_dir / "checkpoints").iterdir() if p.name.startswith(".")]


def test_a_run_killed_by_sigkill_resumes_exactly(tmp_path, whole):
    """A real SIGKILL (no cleanup runs) right after the first checkpoint appears."""
    run_dir = tmp_path / "run"
    cli = [sys.executable, "-c", "import sys; from armeta_rl.cli import train; sys.exit(train())"]
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
    run_training(Job(train_config(*RUN, "trainer.stop_at=4"), run_dir), progress=False)
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
        task = report_errors("armeta-train",
                              lambda cfg: run_training(Job(validate(cfg), run_dir), progress=False))
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
        run_training(Job(train_config(*RUN), tmp_path), progress=False)


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
        run_training(Job(train_config(*RUN), tmp_path), progress=False)
    assert not (tmp_path / "config.yaml").exists()
    holder.kill()
    holder.wait()
    run_training(Job(train_config(*RUN), tmp_path), progress=False)  # the dead holder's lock
    assert (tmp_path / EVAL_FILE).is_file() and not (tmp_path / LOCK_FILE).exists()


def test_two_runs_started_together_into_one_directory(tmp_path, whole):
    cli = [sys.executable, "-c", "import sys; from armeta_rl.cli import train; sys.exit(train())"]
    runs = [subprocess.Popen([*cli, *RUN, f"hydra.run.dir={tmp_path}"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(run.wait(timeout=300), run.stderr.read()) for run in runs]
    codes = sorted(code for code, _ in results)
    assert codes == [0, 2], results
    refused = next(err for code, err in results if code == 2).strip().splitlines()
    assert len(refused) == 1, refused
    # refused by the lock, or (had the other run ended before this one started) by its files
    assert "in use by another run" in refused[0] or "already holds a run" in refused[0]
    assert outcome(tmp_path) == outcome(whole)


def test_the_divergence_bound_stops_the_run_and_names_the_checkpoint(tmp_path, monkeypatch):
    with pytest.raises(TrainingDiverged, match="beyond trainer.max_loss = 0.001.*no checkpoint"):
        run_training(Job(train_config(*RUN, "trainer.max_loss=1e-3"), tmp_path), progress=False)
    run_dir = tmp_path / "later"
    step = game.GameTrainer.train_iteration

    def blows_up_at_3(self):
        """Iteration 3's losses leave a bound that the first two kept."""
        if self.iteration == 2:
            self.options = dataclasses.replace(self.options, max_loss=1e-3)
        return step(self)

    monkeypatch.setattr(game.GameTrainer, "train_iteration", blows_up_at_3)
    with pytest.raises(TrainingDiverged, match="iteration 3.*checkpoint-000000000002 is kept"):
        run_training(Job(train_config(*RUN), run_dir), progress=False)


def test_a_diverged_adversary_step_stops_the_run_at_its_last_good_checkpoint(
    tmp_path, monkeypatch
):
    """The follower's step at iteration 3 leaves φ non-finite: the run stops with one line naming
    the checkpoint of iteration 2, whose φ is finite, and resuming from it is possible."""
    from armeta_rl.risk import adversarial

    step = adversarial.follower_step

    def explodes_at_3(follower, tasks, losses):
        if follower.scheduler.last_epoch == 2:
            follower.optimizer.param_groups[0]["lr"] = 1e300
        return step(follower, tasks, losses)

    run_dir = tmp_path / "run"
    with monkeypatch.context() as patch:
        patch.setattr(adversarial, "follower_step", explodes_at_3)
        with pytest.raises(TrainingDiverged, match="non-finite parameters.*"
                                                   "checkpoint-000000000002 is kept"):
            run_training(Job(train_config(*RUN), run_dir), progress=False)
    _, players = load_players(run_dir, "resume")
    assert all(torch.isfinite(p).all() for p in players.principle.parameters())
    run_training(make_job([f"resume={run_dir}"]), progress=False)
    assert (run_dir / EVAL_FILE).is_file()


def run_cli(monkeypatch, capsys, tool, *args):
    """Run ``armeta-train`` or ``armeta-eval`` (``tool``: its function) in this process, for
    commands refused before Hydra starts; returns (exit code, stderr lines)."""
    return tool(list(args)), capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("override,words", [
    ("learner.maml.first_order=off", "must be a boolean (true or false)"),
    ("learner.maml.first_order=maybe", "must be a boolean (true or false)"),
    ("learner.maml.hidden=abc", "must be a list of integers"),
    ("learner.maml_trpo.max_kl=0", "must be > 0"),
    ("seed=18446744073709551616", "must be in [-2^63, 2^64 - 1]"),
    ("eval.seed=18446744073709551615", "must be in [-2^63, 2^64 - 2]"),
    ("trainer.max_loss=-1", "must be > 0"),
])
def test_bad_values_are_refused_before_hydra(tmp_path, monkeypatch, capsys, override, words):
    run_dir = tmp_path / "run"
    code, err = run_cli(monkeypatch, capsys, train, override, f"hydra.run.dir={run_dir}")
    key = override.split("=")[0]
    assert code == 2 and len(err) == 1 and f"'{key}'" in err[0] and words in err[0], err
    assert not run_dir.exists()


def test_commands_refused_before_hydra_create_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    missing = tmp_path / "nonexistent"
    code, err = run_cli(monkeypatch, capsys, train, f"resume={missing}")
    assert code == 2 and len(err) == 1 and "'resume'" in err[0] and not missing.exists()
    code, err = run_cli(monkeypatch, capsys, train, "-m", "trainer.iterations=5,0")
    assert code == 2 and len(err) == 1, err
    assert "'trainer.iterations' = 0" in err[0] and "(job trainer.iterations=0" in err[0]
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    code, err = run_cli(monkeypatch, capsys, train, f"hydra.run.dir={a_file}")
    assert code == 2 and len(err) == 1 and "is an existing file" in err[0]
    code, err = run_cli(monkeypatch, capsys, train, f"hydra.run.dir={a_file}/run")
    assert code == 2 and len(err) == 1 and "is a file" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]  # no job, no runs/


def test_a_command_refused_inside_its_job_removes_the_directories_it_made(tmp_path):
    refused = tmp_path / "made" / "refused"  # Hydra wrote .hydra/ and a log there, and made its
    result = subprocess.run(  # parent, before the job began
        [sys.executable, "-c", "import sys; from armeta_rl.cli import train; sys.exit(train())",
         "benchmark=point_nav_plain", "eval.support_noise=0.1", f"hydra.run.dir={refused}"],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def evaluate_in_process(capsys, *overrides):
    """``armeta-eval``'s job on ``overrides``; returns (exit code, stderr lines)."""
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        cfg = compose("eval", overrides=list(overrides))
    try:
        report_errors("armeta-eval", _eval_task)(cfg)
    except SystemExit as exit_:
        return exit_.code, capsys.readouterr().err.strip().splitlines()
    return 0, capsys.readouterr().err.strip().splitlines()


def test_eval_refuses_a_broken_checkpoint_and_an_unwritable_out_with_one_line(
    tmp_path, stopped, capsys
):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    out = tmp_path / "no" / "such" / "dir" / "eval.json"
    code, err = evaluate_in_process(capsys, f"learner={run_dir}", f"out={out}")
    assert code == 2 and len(err) == 1 and "'out'" in err[0] and "not a directory" in err[0]
    corrupt(run_dir / "checkpoints" / "checkpoint-000000000004" / FILES["leader"], "half")
    code, err = evaluate_in_process(capsys, f"learner={run_dir}")
    assert code == 2 and len(err) == 1, err
    assert "'learner'" in err[0] and "checkpoint-000000000004 is broken" in err[0]
    (run_dir / "config.yaml").write_text("seed: [0\n")
    code, err = evaluate_in_process(capsys, f"learner={run_dir}")
    assert code == 2 and len(err) == 1 and "config.yaml cannot be read" in err[0], err


def test_a_log_row_that_does_not_parse_is_a_clear_refusal(tmp_path, stopped):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    log = run_dir / CSV_LOG_DIR / "scalars" / "train" / "leader_loss.csv"
    log.write_text(log.read_text() + "garbage,row\n")
    with pytest.raises(ConfigError, match="leader_loss.csv has a row that does not parse"):
        finish(run_dir)
    log.write_text(log.read_text().replace("garbage,row\n", "5,0.3"))  # a torn last row
    finish(run_dir)
    assert "5,0.3" not in log.read_text()


@pytest.mark.parametrize("override,refusal", [
    ("seed=7", "'seed' = 7: cannot change on resume"),
    ("risk.ar.lr=0.1", "'risk.ar.lr' = 0.1: cannot change on resume"),
    ("+trainer.extra=1", "'trainer.extra' = 1: cannot change on resume"),
    ("trainer.iterations=3", "'trainer.iterations' = 3: must be >= 6 on resume"),
    ("trainer.iterations=abc", "'trainer.iterations' = 'abc': must be an integer"),
])
def test_resume_refuses_every_override_but_more_iterations(stopped, override, refusal):
    with pytest.raises((Refused, ConfigError)) as error:
        make_job([f"resume={stopped}", override])
    assert refusal in str(error.value) and "\n" not in str(error.value)


def test_resume_may_switch_keeping_freed_memory(stopped):
    job = make_job([f"resume={stopped}", "trainer.keep_freed_memory=false"])
    assert job.config.trainer.keep_freed_memory is False


def test_resume_with_more_iterations_follows_the_longer_cosine_schedule(tmp_path):
    """A run trained to N1 = 6 iterations and resumed with trainer.iterations = 10 uses, from
    iteration 7 on, exactly the adversary learning rates of a run planned for 10 from the start
    (η_t = η·(1 + cos(π t / 10)) / 2 at update t + 1); its config.yaml then says 10."""
    longer = tmp_path / "longer"
    run_training(Job(train_config(*RUN, "trainer.iterations=10"), longer), progress=False)
    extended = tmp_path / "extended"
    run_training(Job(train_config(*RUN), extended), progress=False)
    run_training(make_job([f"resume={extended}", "trainer.iterations=10"]), progress=False)
    rates = {run: (run / CSV_LOG_DIR / "scalars" / "adversary" / "lr.csv").read_text()
             .splitlines() for run in (longer, extended)}
    assert [int(row.split(",")[0]) for row in rates[extended]] == list(range(1, 11))
    assert rates[extended][6:] == rates[longer][6:]
    assert rates[extended][:6] != rates[longer][:6]  # the first six followed the 6-step plan
    assert float(rates[extended][-1].split(",")[1]) == pytest.approx(0.001 * (1 + math.cos(
        math.pi * 9 / 10)) / 2, rel=1e-12)
    assert "iterations: 10" in (extended / "config.yaml").read_text()
    assert json.loads((extended / EVAL_FILE).read_text())["initial"]["n_tasks"] == 20


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_a_read_only_run_directory_is_refused_before_anything_is_written(tmp_path):
    parent = tmp_path / "read_only"
    parent.mkdir()
    parent.chmod(0o555)
    try:
        with pytest.raises(ConfigError, match=r"cannot be written in .* \(read-only\)"):
            run_training(Job(train_config(*RUN), parent / "run"), progress=False)
        assert not (parent / "run").exists()
    finally:
        parent.chmod(0o755)


def test_an_rl_run_resumes_exactly(tmp_path):
    overrides = (*SMALL_RUN, "benchmark=point_nav_plain", "method=maml", "trainer.iterations=4",
                 "trainer.checkpoint_every=2", "trainer.meta_batch=4", "eval.n_tasks=4")
    run_training(Job(train_config(*overrides), tmp_path / "whole"), progress=False)
    run_training(Job(train_config(*overrides, "trainer.stop_at=2"), tmp_path / "split"),
                 progress=False)
    run_training(make_job([f"resume={tmp_path / 'split'}"]), progress=False)
    assert (tmp_path / "split" / EVAL_FILE).read_text() == (tmp_path / "whole" / EVAL_FILE
                                                             ).read_text()


# Preemption: a signal is a stop request the game loop reads (armeta_rl.preemption) ------------

SIGNALLED = """
import os, signal, sys, time
from armeta_rl.trainers import checkpoint, game
sig, where, times = getattr(signal, sys.argv.pop(1)), sys.argv.pop(1), sys.argv.pop(1)
if where == "iteration":  # while iteration 3 trains
    step = game.GameTrainer.train_iteration
    def train_iteration(self):
        if self.iteration == 2:
            os.kill(os.getpid(), sig)
            if times == "twice":  # after the first one was handled
                time.sleep(0.5)
                os.kill(os.getpid(), sig)
        return step(self)
    game.GameTrainer.train_iteration = train_iteration
else:  # between two payload writes of the checkpoint of iteration 4
    write, calls = checkpoint.write_file, [0]
    def write_file(path, data):
        calls[0] += 1
        if calls[0] == 6:
            os.kill(os.getpid(), sig)
        write(path, data)
    checkpoint.write_file = write_file
from armeta_rl.cli import train
train()
"""


def signalled_cli(run_dir, sig, where, times="once", *extra):
    return subprocess.run([sys.executable, "-c", SIGNALLED, sig, where, times, *RUN, *extra,
                           f"hydra.run.dir={run_dir}"], capture_output=True, text=True,
                          timeout=300)


@pytest.mark.parametrize("sig,where,code,stopped_after", [
    ("SIGTERM", "iteration", 75, 3),
    ("SIGTERM", "checkpoint", 75, 4),
    ("SIGUSR1", "iteration", 75, 3),
    ("SIGUSR1", "checkpoint", 75, 4),
    ("SIGINT", "iteration", 130, 3),
    ("SIGINT", "checkpoint", 130, 4),
])
def test_a_signal_stops_the_run_after_its_iteration_with_a_checkpoint_and_it_resumes_exactly(
        tmp_path, whole, sig, where, code, stopped_after):
    run_dir = tmp_path / "run"
    result = signalled_cli(run_dir, sig, where)
    newest = f"checkpoint-{stopped_after:012d}"
    assert result.returncode == code, result.stderr
    assert result.stderr.strip().splitlines() == [
        f"armeta-train: stopped by {sig} after iteration {stopped_after}: checkpoint "
        f"{run_dir / 'checkpoints' / newest} written; continue with: armeta-train "
        f"resume={run_dir}"]
    assert verify(run_dir / "checkpoints" / newest) is None
    assert not (run_dir / EVAL_FILE).exists()
    finish(run_dir)
    assert outcome(run_dir) == outcome(whole)


def test_a_second_sigint_stops_at_once_keeping_the_last_checkpoint(tmp_path, whole):
    run_dir = tmp_path / "run"
    result = signalled_cli(run_dir, "SIGINT", "iteration", "twice")
    assert result.returncode == 130
    assert result.stderr.strip().splitlines() == [
        f"armeta-train: stopped at once by a second SIGINT: the last checkpoint "
        f"{run_dir / 'checkpoints' / 'checkpoint-000000000002'} is kept; continue with: "
        f"armeta-train resume={run_dir}"]
    finish(run_dir)
    assert outcome(run_dir) == outcome(whole)


def test_a_stop_request_is_read_by_the_game_loop(tmp_path, whole, monkeypatch):
    """In process: the request, not a signal, is what the loop reads; a run asked to stop before
    its first iteration trains none and keeps its config, so resume= starts it."""
    from armeta_rl.errors import RunStopped
    from armeta_rl.preemption import EXIT_PREEMPTED, StopRequest

    stop = StopRequest()
    step = game.GameTrainer.train_iteration

    def requested_during_5(self):
        if self.iteration == 4:
            stop.request(signal.SIGUSR1)
        return step(self)

    monkeypatch.setattr(game.GameTrainer, "train_iteration", requested_during_5)
    run_dir = tmp_path / "run"
    with pytest.raises(RunStopped, match="stopped by SIGUSR1 after iteration 5") as stopped:
        run_training(Job(train_config(*RUN), run_dir), progress=False, stop=stop)
    assert stopped.value.code == EXIT_PREEMPTED
    monkeypatch.undo()
    finish(run_dir)
    assert outcome(run_dir) == outcome(whole)
    before = tmp_path / "before"
    with pytest.raises(RunStopped, match="after iteration 0: no checkpoint yet"):
        run_training(Job(train_config(*RUN), before), progress=False, stop=stop)
    assert (before / "config.yaml").exists() and not (before / "checkpoints").exists()
    finish(before)
    assert outcome(before) == outcome(whole)


def descendants(pid):
    """Every live process below ``pid`` (Linux /proc)."""
    children = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if fields[0] != "Z":
                children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found += [child]
            todo += [child]
    return found


def alive(pid):
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes from /proc")
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_a_stopped_or_killed_sweep_stops_its_workers_with_checkpoints(tmp_path, sig):
    """``armeta-reproduce launcher=local``: SIGTERM to the parent is forwarded to its joblib
    workers, whose runs checkpoint and stop (the parent exits 75); after a SIGKILL of the parent
    the workers notice it is gone and do the same. The progress lines say which runs stopped;
    the jobs the workers had not started yet print nothing (no "FAILED")."""
    results, err, out = tmp_path / "results", tmp_path / "stderr", tmp_path / "stdout"
    with err.open("w") as stderr, out.open("w") as stdout:  # files: workers would hold pipes open
        process = subprocess.Popen(
            [sys.executable, "-c", "from armeta_rl.reproduce.cli import main; main()", "noise",
             "profile=tiny", "benchmarks=sinusoid_uniform", "seeds=0", "launcher=local",
             "jobs=2", "+train.trainer.iterations=100000",
             "+train.trainer.checkpoint_every=100000", f"results={results}"],
            stdout=stdout, stderr=stderr, start_new_session=True)
    deadline = time.monotonic() + 300
    while len(list(results.glob("runs/*/*/*/config.yaml"))) < 2:  # two runs train
        assert process.poll() is None and time.monotonic() < deadline, err.read_text()
        time.sleep(0.2)
    time.sleep(1)
    workers = descendants(process.pid)
    process.send_signal(sig)
    if sig == signal.SIGTERM:
        assert process.wait(timeout=300) == 75
        assert err.read_text().strip().splitlines()[-1] == (
            "armeta-reproduce: stopped by SIGTERM: the runs in flight wrote checkpoints; the "
            "same command continues the sweep")
        events = [line.split()[2] for line in out.read_text().splitlines()
                  if line.startswith("[noise train]")]
        assert sorted(events) == ["start", "start", "stopped", "stopped"], out.read_text()
        assert "not started" not in err.read_text()
    else:
        process.wait(timeout=60)
    while any(alive(pid) for pid in workers):
        assert time.monotonic() < deadline, [pid for pid in workers if alive(pid)]
        time.sleep(0.2)
    stopped = sorted(results.glob("runs/*/*/*/checkpoints/checkpoint-*"))
    assert len(stopped) == 2 and all(verify(path) is None for path in stopped), stopped


@pytest.mark.parametrize("sig,code", [("SIGTERM", 75), ("SIGINT", 130)])
def test_a_stop_signal_abandons_a_scoring_at_once_writing_nothing(tmp_path, whole, sig, code,
                                                                   capsys, monkeypatch):
    """A scoring keeps nothing until its report is written, so a stop signal ends it at once
    (a sweep's evaluation job does not run on to its end): one line, the signal's exit code,
    no report."""
    from armeta_rl.cli import evaluate
    from armeta_rl.preemption import PROCESS
    from armeta_rl.trainers import report

    score, out = report.evaluate_runs, tmp_path / "eval.json"

    def signalled(*args, **kwargs):  # a stop signal while the learner is scored
        os.kill(os.getpid(), getattr(signal, sig))
        return score(*args, **kwargs)

    monkeypatch.setattr(report, "evaluate_runs", signalled)
    monkeypatch.setattr(PROCESS, "signal", None)  # the request this test makes ends with it
    assert in_process(evaluate, [f"learner={whole}", f"out={out}"], capsys) == (
        code, "", f"armeta-eval: scoring {whole} stopped by {sig}: nothing written; the same "
        "command scores it\n")
    assert not out.exists()


def test_a_process_asked_to_stop_starts_no_scoring_and_its_handlers_are_restored():
    from armeta_rl.errors import RunNotStarted, RunStopped
    from armeta_rl.preemption import EXIT_PREEMPTED, StopRequest, abandoning

    before, request = signal.getsignal(signal.SIGTERM), StopRequest()
    stopped = "^work stopped by SIGTERM: nothing written; again$"
    with pytest.raises(RunStopped, match=stopped), abandoning("work", "again", request=request):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler raises before this ends
    assert signal.getsignal(signal.SIGTERM) is before and request.name == "SIGTERM"
    refusal = "^not started: this process received SIGTERM; again$"
    with pytest.raises(RunNotStarted, match=refusal) as refused, abandoning(
            "work", "again", request=request):
        pytest.fail("a process asked to stop started the work")
    assert refused.value.code == EXIT_PREEMPTED


# A finished run, damaged artefacts ------------------------------------------------------------

FRAMES = (*RUN, "trainer.density_every=2")


def test_resuming_a_finished_run_changes_nothing(tmp_path, whole, capsys):
    run_dir = tmp_path / "run"
    shutil.copytree(whole, run_dir)
    files = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file() and p.name != LOCK_FILE}
    report = run_training(make_job([f"resume={run_dir}"]), progress=False)
    assert report == json.loads((whole / EVAL_FILE).read_text())
    assert "has finished: nothing to do" in capsys.readouterr().out
    assert {p: p.read_bytes() for p in files} == files
    rows = (run_dir / CSV_LOG_DIR / "scalars" / "eval" / "initial" / "mean.csv").read_text()
    assert rows.count("\n") == 1


def test_an_evaluation_cut_short_is_logged_once_on_resume(tmp_path, whole, monkeypatch):
    """A crash after the evaluation's scalars were logged and before eval.json (written last):
    the resumed run logs them again, once."""
    run_dir = tmp_path / "run"
    with monkeypatch.context() as patch:
        patch.setattr("armeta_rl.trainers.training.write_text_atomically",
                      lambda path, text: (_ for _ in ()).throw(Killed()))
        with pytest.raises(Killed):
            run_training(Job(train_config(*RUN), run_dir), progress=False)
    assert not (run_dir / EVAL_FILE).exists()
    finish(run_dir)
    assert outcome(run_dir) == outcome(whole)


@pytest.fixture(scope="module")
def framed(tmp_path_factory):
    """The uninterrupted run with density frames at 0, 2, 4 and 6."""
    run_dir = tmp_path_factory.mktemp("framed")
    run_training(Job(train_config(*FRAMES), run_dir), progress=False)
    return run_dir


def test_a_damaged_density_frame_is_left_out_of_the_animation_with_a_warning(
        tmp_path, framed, caplog):
    run_dir = tmp_path / "run"
    run_training(Job(train_config(*FRAMES, "trainer.stop_at=4"), run_dir), progress=False)
    for damaged in ("iter_000002.png", "iter_000002.pt"):  # a frame with its numbers is redrawn
        (run_dir / "density" / damaged).write_bytes(b"")
    with caplog.at_level(logging.WARNING):
        run_training(make_job([f"resume={run_dir}"]), progress=False)
    assert "iter_000002.png cannot be read: left out of density.gif" in caplog.text
    assert outcome(run_dir) == outcome(framed)
    frames = Image.open(run_dir / "density.gif")
    assert frames.n_frames == Image.open(framed / "density.gif").n_frames - 1


def test_every_file_of_a_run_is_written_through_a_staged_sibling(tmp_path, monkeypatch):
    """No file of the run directory but the lock and the CSV rows (appended whole, a torn last
    row dropped on resume) is opened for writing under its own name: each is staged, fsynced
    and renamed (a kill or a full disk leaves the old file or none)."""
    import builtins
    import io

    written, real_open, real_io_open = [], builtins.open, io.open

    def spy(opener):
        def opened(file, mode="r", *args, **kwargs):
            if any(m in mode for m in "wax") and str(tmp_path) in str(file):
                written.append(Path(file))
            return opener(file, mode, *args, **kwargs)
        return opened

    monkeypatch.setattr(builtins, "open", spy(real_open))
    monkeypatch.setattr(io, "open", spy(real_io_open))
    run_training(Job(train_config(*FRAMES), tmp_path / "run"), progress=False)
    monkeypatch.undo()
    staged = [p for p in written if any(part.startswith(".") for part in p.parts)]
    direct = sorted({p.relative_to(tmp_path) for p in written
                     if p not in staged and p.suffix != ".csv"})
    assert staged and direct == [], direct


def test_a_run_whose_checkpoints_were_all_refused_is_refused_again(tmp_path, stopped):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    for checkpoint in (run_dir / "checkpoints").iterdir():
        corrupt(checkpoint / FILES["leader"], "garbled")
    with pytest.raises(CheckpointBroken, match="has no intact checkpoint; broken: checkpoint-0"):
        finish(run_dir)
    with pytest.raises(CheckpointBroken, match="checkpoint-000000000004.broken \\(set aside by an"):
        finish(run_dir)  # not trained again from iteration 0
    assert not (run_dir / EVAL_FILE).exists()


def test_a_lock_refused_chains_no_blocking_io_error(tmp_path):
    """The refusal of a held lock is one ConfigError line, not chained to flock's
    BlockingIOError (whose traceback would follow it)."""
    from armeta_rl.trainers.run_dir import run_lock

    with pytest.raises(ConfigError) as raised, run_lock(tmp_path, "k"), run_lock(tmp_path, "k"):
        pass
    assert raised.value.__cause__ is None and raised.value.__suppress_context__


def test_a_run_saved_before_a_key_was_added_resumes_as_itself(tmp_path, whole, stopped):
    """A run saved by a version without ``risk.ar.step`` and ``risk.ar.max_kl``: its config.yaml
    lacks them and its checkpoints recorded its identity from that config as saved. A resume
    reads them at their defaults (which keep its behaviour), takes its checkpoints as its own
    and ends as the uninterrupted run, its report recording the identity it was saved with."""
    from armeta_rl.trainers.checkpoint import MANIFEST, identity_as_saved, run_identity, seal

    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    config = run_dir / "config.yaml"
    lines = config.read_text().splitlines(keepends=True)
    ar = lines.index("  ar:\n")
    end = next(i for i in range(ar + 1, len(lines)) if not lines[i].startswith("    "))
    older = "".join(line for i, line in enumerate(lines) if not (
        ar < i < end and line.lstrip().startswith(("step:", "max_kl:"))))
    assert len(older) < len(config.read_text())
    config.write_text(older)
    as_saved = identity_as_saved(older)
    merged = run_identity(OmegaConf.to_container(load_run_config(run_dir, "resume"), resolve=True))
    assert as_saved["config_sha256"] != merged["config_sha256"]
    for checkpoint in (run_dir / "checkpoints").glob("checkpoint-*"):
        manifest = json.loads((checkpoint / MANIFEST).read_text())
        manifest["metadata"]["identity"] = as_saved
        (checkpoint / MANIFEST).write_text(json.dumps(manifest))
        seal(checkpoint, as_saved)
    run_training(make_job([f"resume={run_dir}"]), progress=False)
    report = json.loads((run_dir / EVAL_FILE).read_text())
    assert report["config_sha256"] == as_saved["config_sha256"]
    expected = {**outcome(whole)[0], "config_sha256": as_saved["config_sha256"]}
    assert report == expected
    rescored = cross_evaluate(run_dir, None)  # armeta-eval takes its checkpoints too
    assert rescored["config_sha256"] == as_saved["config_sha256"]
    assert rescored["initial"]["mean"] == report["initial"]["mean"]


# Resume keys that change no result --------------------------------------------------------------

@pytest.mark.parametrize("override", [
    "logger=wandb", "logger=none", "trainer.progress=true", "trainer.checkpoint_every=3",
    "trainer.log_every=3", "trainer.density_every=3", "trainer.stop_signals=[SIGUSR2]",
])
def test_resume_takes_the_keys_that_change_no_result(tmp_path, whole, stopped, override):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    run_training(make_job([f"resume={run_dir}", override]), progress=False)
    assert json.loads((run_dir / EVAL_FILE).read_text()) == outcome(whole)[0]


def test_a_resumed_run_says_which_keys_it_took(tmp_path, stopped):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    result = subprocess.run([sys.executable, "-c", "from armeta_rl.cli import train; train()",
                             f"resume={run_dir}", "logger=wandb", "trainer.log_every=3"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert (f"resuming {run_dir} with logger.kind=wandb, logger.project=armeta_rl, "
            "trainer.log_every=3 "
            "(they change no result)") in result.stdout


# Damaged inputs: one line naming the key --------------------------------------------------------

@pytest.mark.parametrize("how", ["empty", "truncated"])
def test_a_damaged_run_config_is_one_line_for_resume_and_eval(tmp_path, stopped, capsys, how):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    config = run_dir / "config.yaml"
    config.write_text("" if how == "empty" else config.read_text()[:200])
    with pytest.raises(ConfigError, match=f"'resume' = '{run_dir}': its config.yaml"):
        make_job([f"resume={run_dir}"])
    code, err = evaluate_in_process(capsys, f"learner={run_dir}")
    assert code == 2 and len(err) == 1 and f"'learner' = '{run_dir}'" in err[0], err


def test_eval_names_the_learner_before_the_report_path_and_checks_out_first(
        tmp_path, stopped, capsys, monkeypatch):
    code, err = evaluate_in_process(capsys, f"learner={tmp_path / 'no' / 'run'}")
    assert code == 2 and len(err) == 1 and "'learner'" in err[0], err
    monkeypatch.setattr("armeta_rl.trainers.report.evaluate_runs",
                        lambda *args: pytest.fail("evaluated before checking out="))
    code, err = evaluate_in_process(capsys, f"learner={stopped}", "out=/proc/armeta/eval.json")
    assert code == 2 and len(err) == 1 and "'out'" in err[0], err


def test_an_empty_run_directory_key_is_refused(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code, err = run_cli(monkeypatch, capsys, train, *SMALL_RUN, "hydra.run.dir=")
    assert code == 2 and err == ["armeta-train: error: config key 'hydra.run.dir' = '': must "
                                 "name a directory"]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("override,key", [
    ("benchmark.space.high=[1e300,3.14]", "benchmark.space.high"),
    ("benchmark.initial.loc=[40,40]", "benchmark.initial.loc"),
])
def test_a_box_no_run_can_use_is_one_line(tmp_path, override, key):
    """A box beyond float32, or a normal p0 with no mass in the box (its density plot had no
    scale), is refused as the players are built, before training."""
    result = subprocess.run(
        [sys.executable, "-c", "from armeta_rl.cli import train; train()", *SMALL_RUN,
         "benchmark=sinusoid_normal", "trainer.density_every=2", override,
         f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, timeout=300)
    err = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(err) == 1 and f"'{key}'" in err[0], result.stderr
    assert not (tmp_path / "run").exists()


def test_a_density_that_underflows_on_the_grid_is_drawn_blank(tmp_path):
    from armeta_rl.plots import plot_density
    from armeta_rl.tasks.distributions import TruncatedNormal
    from armeta_rl.tasks.space import TaskSpace

    space = TaskSpace(["a", "b"], [0.0, 0.0], [1.0, 1.0])
    needle = TruncatedNormal(space, [0.5, 0.5], [1e-30, 1e-30])  # all mass between grid points
    plot_density(needle, needle, tmp_path / "needle.png", points_per_axis=4)
    assert Image.open(tmp_path / "needle.png").size[0] > 0


# Evaluation reports: a schema, and armeta-reproduce marking a run that fails it unfinished ------

@pytest.mark.parametrize("metric", ["mse", "return"])
def test_every_report_summarize_makes_passes_its_schema(metric):
    from armeta_rl.trainers.evaluation import check_report, summarize

    generator = torch.Generator().manual_seed(0)
    for n in (1, 2, 3, 10, 101):
        for _ in range(20):
            losses = torch.randn(n, generator=generator).exp() * 10 ** float(
                torch.randint(-6, 6, (), generator=generator))
            section = summarize(losses.float(), metric, [0.1, 0.5, 0.9, 0.99])
            check_report({"metric": metric, "benchmark": "b", "method": "m", "initial": section})


@pytest.mark.parametrize("edit,words", [
    (lambda r: r["initial"].update(mean=12345), "'initial.cvar.0.5'"),
    (lambda r: r["initial"].update(mean=float("nan")), "'initial.mean' = nan"),
    (lambda r: r.pop("initial"), "no 'initial'"),
    (lambda r: r["initial"].update(sem=r["initial"]["sem"] / 100), "'initial.sem'"),
    (lambda r: r["initial"]["cvar"].update({"0.9": 0.0}), "'initial.cvar.0.9'"),
    (lambda r: r["initial"].update(n_tasks=0), "'initial.n_tasks'"),
    (lambda r: r.update(metric=None), "'metric'"),
])
def test_a_hand_edited_report_fails_its_schema(whole, edit, words):
    from armeta_rl.trainers.evaluation import ReportInvalid, check_report

    report = json.loads((whole / EVAL_FILE).read_text())
    check_report(report, ("initial", "adversarial"))
    edit(report)
    with pytest.raises(ReportInvalid, match=re.escape(words)):
        check_report(report)


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    """table1 at the tiny profile on Sinusoid-U, seed 0 (its next-seed evaluations wait)."""
    from armeta_rl.reproduce.cli import reproduce

    results = tmp_path_factory.mktemp("swept")
    assert reproduce("table1", "tiny", results, launcher="basic",
                     benchmarks=("sinusoid_uniform",), seeds=(0,)) == 1
    return results


SWEPT = {"benchmarks": ("sinusoid_uniform",), "seeds": (0,)}


@pytest.mark.parametrize("damage", ["mean_12345", "nan", "no_initial", "empty", "non_utf8"])
def test_a_report_that_fails_its_schema_is_unfinished_and_made_again(
        tmp_path, swept, damage, capsys):
    from armeta_rl.reproduce.aggregate import train_seconds
    from armeta_rl.reproduce.cli import reproduce
    from armeta_rl.reproduce.plan import make_plan

    results = tmp_path / "results"
    shutil.copytree(swept, results)
    run_dir = results / "runs" / "sinusoid_uniform" / "maml" / "seed0"
    report = run_dir / (EVAL_FILE if damage in ("mean_12345", "nan", "no_initial")
                        else "eval_vs_same_seed.json")
    original = report.read_bytes()
    data = json.loads(original)
    if damage == "mean_12345":
        data["initial"]["mean"] = 12345
    elif damage == "nan":
        data["initial"]["mean"] = float("nan")
    elif damage == "no_initial":
        del data["initial"]
    report.write_text(json.dumps(data))
    if damage in ("empty", "non_utf8"):
        report.write_bytes(b"" if damage == "empty" else b"\xff\xfe{\x00\x93")
    capsys.readouterr()
    assert reproduce("table1", "tiny", results, launcher="none", **SWEPT) == 1
    assert f"{report} is not a finished report" in capsys.readouterr().err
    row = "sinusoid_uniform,maml,,0,initial,False,"
    table = (results / "table1.csv").read_text()
    assert (row in table) == (report.name != EVAL_FILE)  # an eval report only drops its row
    assert "12345" not in table and "nan" not in table
    if damage in ("mean_12345", "empty"):
        assert reproduce("table1", "tiny", results, launcher="basic", **SWEPT) == 1
        made, before = (json.loads(text) for text in (report.read_bytes(), original))
        for paths in ("learner", "adversary"):  # the copy's directories
            made.pop(paths, None), before.pop(paths, None)
        assert made == before  # made again, the same numbers bit for bit
        if report.name == EVAL_FILE:  # its wall time is the run made again's, not the first's
            manifest = OmegaConf.load(results / "reproduce.yaml")
            subdir = str(run_dir.relative_to(results))
            measured = train_seconds(make_plan("table1", "tiny", benchmarks=SWEPT["benchmarks"],
                                               seeds=SWEPT["seeds"]), results, {})
            assert manifest.train_seconds[subdir] == measured[subdir]


@pytest.mark.parametrize("damage,words", [
    ("file", "is an existing file"),
    ("proc", "cannot be written in /proc"),
    ("garbled", "its reproduce.yaml cannot be read"),
    ("not_a_manifest", "its reproduce.yaml is not a manifest"),
])
def test_a_results_directory_that_cannot_be_used_is_one_line(
        tmp_path, swept, monkeypatch, capsys, damage, words):
    from armeta_rl.reproduce.cli import main

    results = tmp_path / "results"
    if damage == "file":
        results.write_text("")
    elif damage == "proc":
        results = Path("/proc/armeta-results")
    else:
        shutil.copytree(swept, results)
        (results / "reproduce.yaml").write_text(
            "experiment: [table1\n" if damage == "garbled" else "- a\n- list\n")
    monkeypatch.setattr(sys, "argv", ["armeta-reproduce", "table1", "profile=tiny",
                                      "launcher=none", f"results={results}"])
    with pytest.raises(SystemExit) as exit_:
        main()
    code, err = exit_.value.code, capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert f"'results' = '{results}'" in err[0] and words in err[0], err


def test_an_unfinished_run_with_a_damaged_config_is_one_line_in_its_sweep(
        tmp_path, swept, capsys):
    from armeta_rl.reproduce.cli import reproduce

    results = tmp_path / "results"
    shutil.copytree(swept, results)
    run_dir = results / "runs" / "sinusoid_uniform" / "maml" / "seed0"
    (run_dir / EVAL_FILE).unlink()
    (run_dir / "config.yaml").write_text("")
    assert reproduce("table1", "tiny", results, launcher="basic", **SWEPT) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert f"config key 'resume' = '{run_dir}': its config.yaml is incomplete" in err[0]


def test_ray_joins_a_given_cluster_without_the_local_object_store_size(monkeypatch):
    import socket

    from armeta_rl.reproduce.launch import check_ray_address, launcher_overrides

    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    assert launcher_overrides("ray", None) == ["hydra/launcher=ray"]
    assert launcher_overrides("ray", None, ["hydra.launcher.ray.init.address=10.0.0.1:6379"]) == [
        "hydra/launcher=ray", "+hydra.launcher.ray.init.object_store_memory=null"]
    with socket.socket() as listening:
        listening.bind(("127.0.0.1", 0))
        listening.listen()
        check_ray_address(f"127.0.0.1:{listening.getsockname()[1]}")  # it answers
        closed = listening.getsockname()[1]
    with pytest.raises(ConfigError, match=r"'hydra.launcher.ray.init.address' = '127.0.0.1:\d+': "
                       "nothing answers there"):
        check_ray_address(f"127.0.0.1:{closed}")
    with pytest.raises(ConfigError, match="allowed: host:port"):
        check_ray_address("no-port")


# Sizes and threads this machine cannot run ------------------------------------------------------

@pytest.mark.parametrize("override,key,words", [
    ("threads=100000", "threads", r"must be <= \d+, the CPUs this process may run on"),
    ("eval.n_tasks=100000000", "eval.n_tasks", r"needs at least .*: allowed: at most \d+$"),
    ("trainer.meta_batch=100000000", "trainer.meta_batch",
     r"needs at least .*: allowed: at most \d+$"),
    ("risk.ar.initial_samples=1000000000000", "risk.ar.initial_samples",
     r"needs at least .*: allowed: at most \d+$"),
])
def test_a_size_beyond_this_machine_is_one_line_before_anything_is_allocated(
        tmp_path, monkeypatch, capsys, override, key, words):
    run_dir = tmp_path / "run"
    code, err = run_cli(monkeypatch, capsys, train, *SMALL_RUN, override,
                        f"hydra.run.dir={run_dir}")
    assert code == 2 and len(err) == 1, err
    value = override.split("=")[1]
    assert re.search(f"config key '{re.escape(key)}' = {value}: {words}", err[0]), err
    assert not run_dir.exists()


@pytest.mark.parametrize("benchmark", ["sinusoid_uniform", "pendulum_uniform", "point_nav_plain"])
def test_the_memory_bound_is_below_what_an_evaluation_allocates(benchmark):
    """The bound a size is refused by (armeta_rl.resources.task_batch_bytes) is at most the bytes
    torch allocates while the leader collects and evaluates the batch: a size it refuses could
    not run."""
    from torch.profiler import ProfilerActivity, profile

    from armeta_rl.config import validate
    from armeta_rl.resources import hidden_units, task_batch_bytes
    from armeta_rl.trainers.players import build_players

    config = validate(compose_train(*SMALL_RUN, f"benchmark={benchmark}", "method=maml",
                                    "trainer.meta_batch=3"))
    players = build_players(config)
    tasks = players.initial.sample(3)
    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as profiled:
        players.leader.evaluate(players.leader.collect(tasks, players.eval_collector))
    allocated = sum(event.self_cpu_memory_usage for event in profiled.events()
                    if event.self_cpu_memory_usage > 0)
    units = min(hidden_units(options) for name, options in config.learner.items()
                if name == config.method.learner or name.startswith(f"{config.method.learner}_"))
    assert 0 < task_batch_bytes(3, config.benchmark.eval_collector, units) <= allocated


def test_a_checkpoint_of_another_run_is_refused_on_resume_and_eval(tmp_path, stopped):
    """A seed-4 run's checkpoints copied into a seed-0 run's directory: resuming it, evaluating
    it, or loading it as a frozen leader refuses them as another run's (its seed differs), and
    nothing is trained or written."""
    other = tmp_path / "other"
    run_training(Job(train_config(*RUN, "seed=4", "trainer.stop_at=2"), other), progress=False)
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    shutil.rmtree(run_dir / "checkpoints")
    shutil.copytree(other / "checkpoints", run_dir / "checkpoints")
    with pytest.raises(ConfigError, match="is another run's: seed 4 \\(this run: 0\\)"):
        finish(run_dir)
    with pytest.raises(ConfigError, match="is another run's: seed 4"):
        load_players(run_dir, "learner")
    assert not (run_dir / EVAL_FILE).exists()
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == [
        "checkpoint-000000000002"]


def test_a_lock_file_that_is_a_link_is_refused_and_its_target_untouched(tmp_path, stopped):
    """run.lock replaced by a link to another file: resume refuses it in one line and neither
    writes into the target nor removes the link."""
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    target = tmp_path / "precious.txt"
    target.write_text("keep me\n")
    (run_dir / LOCK_FILE).symlink_to(target)
    with pytest.raises(ConfigError, match="its run.lock is a link, not a lock file a run made"):
        finish(run_dir)
    assert target.read_text() == "keep me\n" and (run_dir / LOCK_FILE).is_symlink()


@pytest.mark.parametrize(("how", "words"), [
    ("dangling link", "is a link to nothing"),
    ("link loop", "cannot be used (Too many levels of symbolic links)"),
    ("long component", "cannot be used (File name too long)"),
])
def test_a_run_directory_the_file_system_cannot_use_is_one_line(tmp_path, capsys, how, words):
    run_dir = tmp_path / ("x" * 300 if how == "long component" else "run")
    if how == "dangling link":
        run_dir.symlink_to(tmp_path / "nowhere")
    elif how == "link loop":
        run_dir.symlink_to(run_dir)
    assert train([*SMALL_RUN, f"hydra.run.dir={run_dir}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err


@pytest.mark.parametrize("kind", ["fifo", "link to /dev/zero"])
def test_a_report_or_out_that_is_no_regular_file_is_refused(tmp_path, whole, capsys, kind):
    """An eval.json that is a pipe or a link to /dev/zero is refused without being read, and
    armeta-eval's out= refuses a target that is not a regular file, leaving it as it was."""
    from armeta_rl.cli import evaluate
    from armeta_rl.trainers.evaluation import ReportInvalid, read_report

    path = tmp_path / "eval.json"
    if kind == "fifo":
        os.mkfifo(path)
    else:
        path.symlink_to("/dev/zero")
    with pytest.raises(ReportInvalid, match="not a regular file"):
        read_report(path)
    assert evaluate([f"learner={whole}", f"out={path}"]) == 2
    assert "is not a regular file" in capsys.readouterr().err
    assert path.is_symlink() or path.is_fifo()


@pytest.mark.parametrize("lost", [("iter_000004.png",), ("iter_000004.png", "iter_000004.pt")])
def test_a_frame_a_kill_cut_off_after_its_checkpoint_is_drawn_on_resume(tmp_path, framed, lost):
    """A kill just after the checkpoint of iteration 4, before its density frame was drawn (or
    its numbers saved): the resumed run draws it from the checkpoint's p_φ, so its animation
    equals the uninterrupted run's frame for frame."""
    run_dir = tmp_path / "run"
    run_training(Job(train_config(*FRAMES, "trainer.stop_at=4"), run_dir), progress=False)
    for name in lost:
        (run_dir / "density" / name).unlink()
    run_training(make_job([f"resume={run_dir}"]), progress=False)
    ours, theirs = Image.open(run_dir / "density.gif"), Image.open(framed / "density.gif")
    assert ours.n_frames == theirs.n_frames
    for index in range(ours.n_frames):
        ours.seek(index)
        theirs.seek(index)
        assert ours.convert("RGB").tobytes() == theirs.convert("RGB").tobytes()


@pytest.mark.parametrize(("entry", "program"), [
    ("from armeta_rl.cli import train as main", "armeta-train"),
    ("from armeta_rl.cli import evaluate as main", "armeta-eval"),
    ("from armeta_rl.reproduce.entry import main", "armeta-reproduce"),
])
def test_a_memory_limit_too_small_to_load_torch_is_one_line_and_exit_code_2(
        tmp_path, entry, program):
    """Under a 600 MiB address-space limit an import of torch, NumPy or MuJoCo may abort
    (``std::bad_alloc``), exit from OpenBLAS or leave no memory to say why: each entry point
    refuses before it imports them, naming the limit and the floor, and writes nothing."""
    import resource

    def limited():
        resource.setrlimit(resource.RLIMIT_AS, (600 * 2**20, 600 * 2**20))

    done = subprocess.run(
        [sys.executable, "-c", f"import sys; {entry}; sys.exit(main())", *SMALL_RUN,
         f"hydra.run.dir={tmp_path / 'run'}"], preexec_fn=limited, cwd=tmp_path,
        capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr[-2000:]
    assert done.stderr.strip().splitlines() == [
        f"{program}: error: out of memory: this process's address-space limit (ulimit -v) "
        "is 600 MiB, below the 1024 MiB that loading torch and MuJoCo needs: raise it, or lift "
        "it (ulimit -v unlimited)"], done.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_library_the_loader_cannot_map_is_out_of_memory_only_under_a_limit():
    """The loader's "failed to map segment" under an address-space limit (where it means no
    room), from an import or from a library Ray loads, is the out-of-memory line and exit code 2,
    as MuJoCo's "Could not allocate memory" is anywhere; without a limit the ``ImportError`` is
    a bug (no line: its traceback) and the ``OSError`` a file that could not be read."""
    check = (
        "import resource; from armeta_rl.cli.failures import failure; "
        "mapped = ImportError('ft2font.so: failed to map segment from shared object'); "
        "loaded = OSError('_raylet.so: failed to map segment from shared object'); "
        "mujoco = ValueError('Error: engine error: Could not allocate memory'); "
        "print(failure(mapped), failure(loaded), failure(mujoco), sep='|'); "
        "resource.setrlimit(resource.RLIMIT_AS, (64 * 2**30, resource.RLIM_INFINITY)); "
        "print(failure(mapped), failure(loaded), failure(mujoco), sep='|')")
    done = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True,
                          timeout=60, check=True)
    oom = (2, f"error: {OUT_OF_MEMORY}")
    assert done.stdout.splitlines() == [
        f"None|{(1, 'error: _raylet.so: failed to map segment from shared object')}|{oom}",
        f"{oom}|{oom}|{oom}"]


def test_a_resume_into_another_hydra_run_dir_logs_into_its_own_directory(tmp_path, stopped):
    run_dir, elsewhere = tmp_path / "run", tmp_path / "elsewhere"
    shutil.copytree(stopped, run_dir)
    assert train([f"resume={run_dir}", f"hydra.run.dir={elsewhere}"]) == 0
    assert "iteration 6" in (run_dir / "armeta-train.log").read_text()
    assert not elsewhere.exists()


def test_checkpoints_that_are_a_file_are_refused_before_training(tmp_path, stopped):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    shutil.rmtree(run_dir / "checkpoints")
    (run_dir / "checkpoints").write_text("not a directory\n")
    with pytest.raises(ConfigError, match="its checkpoints is not a directory"):
        finish(run_dir)
    assert not (run_dir / EVAL_FILE).exists()


@pytest.mark.parametrize("where", ["leader", "manifest"])
def test_a_folder_or_link_where_a_checkpoint_file_belongs_is_refused_naming_it(
        tmp_path, stopped, where):
    """The newest checkpoint's leader payload replaced by a folder, or its manifest by a link to
    /dev/zero (read without bound it would never end): no write of a run leaves either, so the
    checkpoint is refused naming the file, not taken for a broken one an older checkpoint
    stands in for; nothing is trained."""
    run_dir = tmp_path / "run"
    shutil.copytree(stopped, run_dir)
    newest = run_dir / "checkpoints" / "checkpoint-000000000004"
    path = newest / (FILES["leader"] if where == "leader" else MANIFEST)
    path.unlink()
    path.mkdir() if where == "leader" else path.symlink_to("/dev/zero")
    with pytest.raises(FileRefused, match="is a link|is not part of a checkpoint"):
        verify(newest)
    with pytest.raises(ConfigError, match=f"its {path.relative_to(run_dir)} is"):
        finish(run_dir)
    assert newest.is_dir() and not (run_dir / EVAL_FILE).exists()
