"""Attack runs (``trainer.frozen_leader``): an AR run whose learner is another run's finished
learner, loaded and never trained, so that only its adversary learns against that learner."""

import json
import shutil
import subprocess
import sys

import pytest
import torch

from armeta_rl.errors import ConfigError
from armeta_rl.job import Job
from armeta_rl.trainers.players import build_players, load_players
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, cross_evaluate, train_config

TRAIN = [sys.executable, "-c", "from armeta_rl.cli import train; train()"]
RUN = (*SMALL_RUN, "trainer.meta_batch=5", "trainer.checkpoint_every=2", "logger=csv",
       "trainer.log_every=1")


@pytest.fixture(scope="module")
def target(tmp_path_factory):
    """A finished MAML run: the learner attacked."""
    run_dir = tmp_path_factory.mktemp("maml")
    run_training(Job(train_config(*RUN, "method=maml"), run_dir), progress=False)
    return run_dir


def attack(target, *overrides):
    return train_config(*RUN, "method=ar_maml", f"trainer.frozen_leader={target}", *overrides)


@pytest.fixture(scope="module")
def attacked(tmp_path_factory, target):
    """The attack on ``target``, uninterrupted."""
    run_dir = tmp_path_factory.mktemp("attack")
    run_training(Job(attack(target), run_dir), progress=False)
    return run_dir


def parameters(players):
    return [p.detach().clone() for p in players.leader.model.parameters()]


def test_the_learner_stays_and_the_adversary_learns_against_it(target, attacked):
    _, source = load_players(target, "learner")
    _, players = load_players(attacked, "learner")
    assert all(torch.equal(a, b) for a, b in zip(parameters(source), parameters(players)))
    report = json.loads((attacked / "eval.json").read_text())
    scored = json.loads((target / "eval.json").read_text())
    assert report["initial"] == scored["initial"]  # the same learner on the same p0 tasks
    initial_phi = build_players(attack(target)).principle.parameters()
    assert not all(torch.equal(a, b) for a, b in zip(players.principle.parameters(), initial_phi))
    logged = (attacked / "logs" / "scalars" / "adversary" / "objective.csv").read_text()
    assert len(logged.splitlines()) == 6
    # armeta-eval scores any learner on the attack's adversary: the attacked learner gets the
    # attack run's own numbers.
    again = cross_evaluate(target, attacked)
    assert again["adversarial"] == report["adversarial"]


def outcome(run_dir):
    scalars = run_dir / "logs" / "scalars"
    logs = {str(p.relative_to(scalars)): p.read_text() for p in sorted(scalars.rglob("*.csv"))
            if not str(p.relative_to(scalars)).startswith("time")}
    return json.loads((run_dir / "eval.json").read_text()), logs


def test_an_attack_resumes_exactly_without_its_target(tmp_path, target, attacked):
    source = tmp_path / "maml"
    shutil.copytree(target, source)
    run_dir = tmp_path / "attack"
    assert run_training(Job(attack(source, "trainer.stop_at=4"), run_dir), progress=False) is None
    shutil.rmtree(source)  # the checkpoint holds the learner: the target is not needed again
    resumed = subprocess.run([*TRAIN, f"resume={run_dir}"], capture_output=True, text=True,
                             timeout=120)
    assert resumed.returncode == 0, resumed.stderr
    assert outcome(run_dir) == outcome(attacked)


@pytest.mark.parametrize(
    "overrides,words",
    [
        (["method=maml"], "needs a method with a flow adversary (ar_*), not maml"),
        (["method=ar_cnp"], "its method.learner = 'maml' differs from this run's 'cnp'"),
        (["learner.maml.inner_lr=0.1"], "its learner.maml.inner_lr = 0.01 differs"),
        (["benchmark=sinusoid_normal"], "its benchmark.initial.kind = 'uniform' differs"),
    ],
)
def test_a_learner_that_does_not_fit_is_refused(tmp_path, target, overrides, words):
    with pytest.raises(ConfigError, match="trainer.frozen_leader") as error:
        run_training(Job(attack(target, *overrides), tmp_path / "run"), progress=False)
    assert words in str(error.value)
    assert not (tmp_path / "run" / "config.yaml").exists()


def test_an_unfinished_or_missing_target_gets_one_line_and_exit_code_2(tmp_path, target):
    unfinished = tmp_path / "unfinished"
    run_training(Job(train_config(*RUN, "method=maml", "trainer.stop_at=2"), unfinished),
                 progress=False)
    for source, words in ((unfinished, "has not finished (no eval.json)"),
                          (tmp_path / "nothing", "is not a run directory")):
        result = subprocess.run(
            [*TRAIN, *RUN, "method=ar_maml", f"trainer.frozen_leader={source}",
             f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, timeout=120)
        assert result.returncode == 2, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr
        assert "'trainer.frozen_leader'" in result.stderr and words in result.stderr
        assert not (tmp_path / "run").exists()
