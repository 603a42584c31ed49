"""The game loop end to end: maml and ar_maml runs, exact resume, and divergence handling."""

import json
import subprocess
import sys

import pytest
import torch

from armeta_rl.config import TrainerConfig, validate
from armeta_rl.errors import TrainingDiverged
from armeta_rl.job import Job
from armeta_rl.trainers.checkpoint import RunCheckpoint
from armeta_rl.trainers.game import GameTrainer
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, compose_train, players_of, train_config


@pytest.mark.parametrize("method", ["maml", "ar_maml"])
def test_training_writes_a_complete_run_directory(tmp_path, method):
    report = run_training(Job(train_config(*SMALL_RUN, f"method={method}", "logger=csv"), tmp_path))
    saved = json.loads((tmp_path / "eval.json").read_text())
    assert saved == report
    assert saved["metric"] == "mse" and saved["initial"]["n_tasks"] == 20
    assert set(saved["initial"]["cvar"]) == {"0.5", "0.7", "0.9"}
    assert (tmp_path / "config.yaml").is_file()
    assert (tmp_path / "logs" / "scalars" / "train" / "leader_loss.csv").is_file()
    assert len(list((tmp_path / "checkpoints").iterdir())) == 2
    has_adversary = method == "ar_maml"
    assert ("adversarial" in saved) == has_adversary
    assert (tmp_path / "density.png").is_file() == has_adversary
    if has_adversary:
        log = tmp_path / "logs" / "scalars" / "adversary" / "objective.csv"
        assert len(log.read_text().splitlines()) == 3  # iterations 2, 4, 6


def test_training_lowers_the_query_loss(tmp_path):
    cfg = compose_train(
        *SMALL_RUN, "trainer.iterations=150", "trainer.checkpoint_every=150", "method=maml"
    )
    players = players_of(cfg)
    before = run_training_eval(players, cfg)
    run_training(Job(validate(cfg), tmp_path))
    after = json.loads((tmp_path / "eval.json").read_text())["initial"]["mean"]
    assert after < 0.8 * before


def run_training_eval(players, cfg):
    from armeta_rl.trainers.evaluation import evaluate_on

    report = evaluate_on(
        players.leader,
        players.initial,
        players.eval_collector,
        cfg.eval.n_tasks,
        [0.5],
        cfg.eval.seed,
    )
    return report["mean"]


def test_resume_through_the_cli_ends_exactly_like_an_uninterrupted_run(tmp_path):
    overrides = [*SMALL_RUN, "method=ar_maml"]
    run_training(Job(train_config(*overrides), tmp_path / "whole"))
    cli = [sys.executable, "-c", "from armeta_rl.cli import train; train()"]
    stopped = subprocess.run(
        [*cli, *overrides, "trainer.stop_at=3", f"hydra.run.dir={tmp_path / 'split'}"],
        capture_output=True,
        text=True,
    )
    assert stopped.returncode == 0, stopped.stderr
    assert not (tmp_path / "split" / "eval.json").exists()
    resumed = subprocess.run([*cli, f"resume={tmp_path / 'split'}"], capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    whole = json.loads((tmp_path / "whole" / "eval.json").read_text())
    split = json.loads((tmp_path / "split" / "eval.json").read_text())
    assert split == whole


class PoisonedCollector:
    """A real sinusoid collector whose labels turn NaN from the ``bad_call``-th call on."""

    def __init__(self, collector, bad_call):
        self.collector, self.bad_call, self.calls = collector, bad_call, 0

    def collect(self, tasks, policy_params=None):
        self.calls += 1
        data = self.collector.collect(tasks)
        if self.calls >= self.bad_call:
            data["query", "y"] = data["query", "y"] * float("nan")
        return data


def test_nan_loss_stops_training_and_keeps_the_last_good_checkpoint(tmp_path):
    cfg = compose_train(*SMALL_RUN, "method=maml")
    players = players_of(cfg)
    players.leader.collector = PoisonedCollector(players.leader.collector, bad_call=6)
    checkpoint = RunCheckpoint(tmp_path, players.leader, players.principle)
    trainer = GameTrainer(
        players.leader,
        players.principle,
        TrainerConfig(iterations=10, meta_batch=5, checkpoint_every=2, progress=False),
        checkpoint=checkpoint,
    )
    with pytest.raises(TrainingDiverged, match="iteration 6"):
        trainer.run()
    assert checkpoint.restore("resume") == 4
    assert all(torch.isfinite(p).all() for p in players.leader.model.parameters())


def test_the_followers_loss_averages_independent_rollouts():
    """trainer.follower_rollouts = R: a task's loss for the follower is the mean of R independent
    fresh rollouts at θ, so its variance over draws is 1/R of one rollout's."""
    from tensordict import TensorDict

    cfg = compose_train("benchmark=point_nav", "method=ar_maml", "trainer.meta_batch=2",
                        "benchmark.collector.episodes=2", "benchmark.collector.max_steps=10")
    players = players_of(cfg)
    tasks = TensorDict({"params": torch.tensor([[0.3, -0.2]]).expand(400, 2)}, [400])
    variances = []
    for rollouts in (1, 4):
        trainer = GameTrainer(players.leader, players.principle, TrainerConfig(
            iterations=1, meta_batch=2, progress=False, follower_rollouts=rollouts))
        torch.manual_seed(rollouts)
        variances.append(float(trainer.fresh_losses(tasks).double().var()))
    assert 4 / 1.6 < variances[0] / variances[1] < 4 * 1.6


def test_a_follower_on_the_steps_losses_reads_them_and_collects_nothing_more():
    """trainer.follower_at: at θ_{t+1} (``next``) an on-policy iteration collects twice more for
    the follower (pre- and post-adaptation episodes afresh); on the step's own losses
    (``step``) it collects only the leader's two rollouts and hands the step's losses on."""
    cfg = compose_train("benchmark=point_nav", "method=ar_maml", "trainer.meta_batch=2",
                        "benchmark.collector.episodes=2", "benchmark.collector.max_steps=10")
    players = players_of(cfg)
    collector, calls = players.leader.collector, []
    collect = collector.collect

    def counted(*args, **kwargs):
        calls.append(1)
        return collect(*args, **kwargs)

    collector.collect = counted
    for follower_at, rollouts in (("next", 4), ("step", 2)):
        trainer = GameTrainer(players.leader, players.principle, TrainerConfig(
            iterations=1, meta_batch=2, progress=False, follower_at=follower_at))
        calls.clear()
        trainer.train_iteration()
        assert len(calls) == rollouts
    step_losses = torch.tensor([1.0, 2.0])
    assert trainer.follower_losses(None, None, step_losses) is step_losses
