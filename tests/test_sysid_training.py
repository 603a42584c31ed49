"""A short ar_maml run on every system-identification benchmark lowers the query MSE; the
evaluation collects data with the training collector's options."""

import json

import pytest

from armeta_rl.config import validate
from armeta_rl.job import Job
from armeta_rl.trainers.evaluation import evaluate_on
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, compose_train, players_of


@pytest.mark.parametrize(
    "benchmark", ["pendulum_uniform", "pendulum_normal", "acrobot_uniform", "acrobot_normal"]
)
def test_short_ar_maml_run_lowers_query_mse(tmp_path, benchmark):
    cfg = compose_train(
        *SMALL_RUN,
        f"benchmark={benchmark}",
        "method=ar_maml",
        "trainer.iterations=40",
        "trainer.checkpoint_every=40",
        "trainer.meta_batch=8",
    )
    untrained = players_of(cfg)
    before = evaluate_on(
        untrained.leader,
        untrained.initial,
        untrained.eval_collector,
        cfg.eval.n_tasks,
        [0.5],
        cfg.eval.seed,
    )["mean"]
    run_training(Job(validate(cfg), tmp_path))
    after = json.loads((tmp_path / "eval.json").read_text())["initial"]["mean"]
    assert after < 0.7 * before


@pytest.mark.parametrize(
    ("benchmark", "override", "attribute", "value"),
    [
        ("pendulum_uniform", "benchmark.collector.target=next", "target", "next"),
        ("acrobot_normal", "benchmark.collector.normalize=scale", "normalize", "scale"),
        ("point_nav_plain", "benchmark.collector.max_steps=30", "max_steps", 30),
    ],
)
def test_evaluation_collects_data_the_way_training_does(benchmark, override, attribute, value):
    players = players_of(compose_train(f"benchmark={benchmark}", override))
    assert getattr(players.leader.collector, attribute) == value
    assert getattr(players.eval_collector, attribute) == value
