"""Fault injection: runs killed at random points, checkpoint files truncated or garbled, a full
disk, concurrent starts. Each case asserts that nothing is lost: the run resumes to exactly the
uninterrupted run's evaluation and logs, or it is refused with a clear error."""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import math
import os
import random
import shutil
import subprocess
import sys
import time

import pytest
import torch
from conftest import SMALL_RUN, compose_train
from hydra import compose, initialize_config_dir

import armeta_rl.trainers.checkpoint as checkpoint_module
from armeta_rl.cli import Refused, _eval_task, _report_errors, config_dir, resume_config, train
from armeta_rl.errors import CheckpointBroken, ConfigError, RunDirectoryError, TrainingDiverged
from armeta_rl.trainers import game
from armeta_rl.trainers.checkpoint import MANIFEST, verify
from armeta_rl.trainers.players import load_players
from armeta_rl.trainers.report import EVAL_FILE, cross_evaluate
from armeta_rl.trainers.run_dir import CSV_LOG_DIR, LOCK_FILE
from armeta_rl.trainers.training import run_training

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
    rng = random.Random(29)
    kill_points = rng.sample(range(1, points + 1), KILLS)
    expected = outcome(whole)
    for n, kill_at in enumerate(kill_points):
        run_dir = tmp_path / f"killed_at_{kill_at}"
        with monkeypatch.context() as patch:
            FaultPoints(patch, kill_at)
            with pytest.raises(Killed):
                run_training(compose_train(*RUN), run_dir, progress=False)
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
        task = _report_errors("armeta-train",
                              lambda cfg: run_training(cfg, run_dir, progress=False))
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
            run_training(compose_train(*RUN), run_dir, progress=False)
    _, players = load_players(run_dir, "resume")
    assert all(torch.isfinite(p).all() for p in players.principle.parameters())
    run_training(compose_train(*RUN, f"resume={run_dir}"), run_dir, progress=False)
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
        _report_errors("armeta-eval", _eval_task)(cfg)
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
        resume_config(str(stopped), [f"resume={stopped}", override])
    assert refusal in str(error.value) and "\n" not in str(error.value)


def test_resume_may_switch_keeping_freed_memory(stopped):
    cfg = resume_config(str(stopped), [f"resume={stopped}", "trainer.keep_freed_memory=false"])
    assert cfg.trainer.keep_freed_memory is False


def test_resume_with_more_iterations_follows_the_longer_cosine_schedule(tmp_path):
    """A run trained to N1 = 6 iterations and resumed with trainer.iterations = 10 uses, from
    iteration 7 on, exactly the adversary learning rates of a run planned for 10 from the start
    (η_t = η·(1 + cos(π t / 10)) / 2 at update t + 1); its config.yaml then says 10."""
    longer = tmp_path / "longer"
    run_training(compose_train(*RUN, "trainer.iterations=10"), longer, progress=False)
    extended = tmp_path / "extended"
    run_training(compose_train(*RUN), extended, progress=False)
    cfg = resume_config(str(extended), [f"resume={extended}", "trainer.iterations=10"])
    run_training(cfg, extended, progress=False)
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
        with pytest.raises(ConfigError, match="cannot be written: .* is read-only"):
            run_training(compose_train(*RUN), parent / "run", progress=False)
        assert not (parent / "run").exists()
    finally:
        parent.chmod(0o755)


def test_an_rl_run_resumes_exactly(tmp_path):
    overrides = (*SMALL_RUN, "benchmark=point_nav_plain", "method=maml", "trainer.iterations=4",
                 "trainer.checkpoint_every=2", "trainer.meta_batch=4", "eval.n_tasks=4")
    run_training(compose_train(*overrides), tmp_path / "whole", progress=False)
    run_training(compose_train(*overrides, "trainer.stop_at=2"), tmp_path / "split",
                 progress=False)
    run_training(compose_train(*overrides, f"resume={tmp_path / 'split'}"), tmp_path / "split",
                 progress=False)
    assert (tmp_path / "split" / EVAL_FILE).read_text() == (tmp_path / "whole" / EVAL_FILE
                                                             ).read_text()
