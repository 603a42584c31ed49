"""A short ar_maml run on every system-identification benchmark lowers the query MSE."""

import json

import pytest
from conftest import SMALL_RUN, compose_train

from armeta_rl.trainers.evaluation import evaluate_on
from armeta_rl.trainers.run import run_training
from armeta_rl.trainers.runs import build_players


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
    untrained = build_players(cfg)
    before = evaluate_on(
        untrained.leader,
        untrained.initial,
        untrained.eval_collector,
        cfg.eval.n_tasks,
        [0.5],
        cfg.eval.seed,
    )["mean"]
    run_training(cfg, tmp_path)
    after = json.loads((tmp_path / "eval.json").read_text())["initial"]["mean"]
    assert after < 0.7 * before
