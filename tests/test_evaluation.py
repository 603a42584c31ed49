"""Evaluation metrics: CVaR_α on hand-made vectors, the standard error of the mean, and the
noisy-support (random perturbation) evaluation."""

import math

import pytest
import torch
from conftest import SMALL_RUN, compose_train, players_of

from armeta_rl.collectors import NoisySupport, SinusoidCollector
from armeta_rl.config import validate
from armeta_rl.tasks import BoxUniform, TaskSpace
from armeta_rl.trainers.evaluation import cvar, summarize
from armeta_rl.trainers.report import evaluate_players


def test_cvar_is_mean_of_the_worst_tail_of_losses():
    losses = torch.arange(1.0, 11.0)  # 1 … 10
    assert cvar(losses, 0.5) == pytest.approx((6 + 7 + 8 + 9 + 10) / 5)
    assert cvar(losses, 0.7) == pytest.approx((8 + 9 + 10) / 3)
    assert cvar(losses, 0.9) == pytest.approx(10.0)


def test_cvar_of_returns_takes_the_lowest():
    returns = torch.tensor([-1.0, -5.0, -2.0, -8.0])
    assert cvar(returns, 0.5, higher_better=True) == pytest.approx((-8 - 5) / 2)


def test_cvar_tail_rounds_up_and_keeps_one_value():
    losses = torch.tensor([3.0, 1.0, 2.0])
    assert cvar(losses, 0.5) == pytest.approx((3 + 2) / 2)  # ceil(1.5) = 2
    assert cvar(losses, 0.99) == pytest.approx(3.0)


def test_cvar_rejects_alpha_outside_unit_interval():
    with pytest.raises(ValueError):
        cvar(torch.ones(3), 1.0)


def test_summary_of_returns_negates_losses():
    report = summarize(torch.tensor([1.0, 3.0]), "return", [0.5])
    assert report == {"mean": -2.0, "sem": 1.0, "cvar": {"0.5": -3.0}, "n_tasks": 2}


def test_standard_error_is_the_spread_of_means_over_task_draws():
    torch.manual_seed(0)
    per_task = torch.distributions.Gamma(2.0, 0.5).sample((20_000, 50))
    sems = torch.tensor([summarize(row, "mse", [0.5])["sem"] for row in per_task[:200]])
    spread_of_means = per_task.double().mean(-1).std()
    assert sems.mean() == pytest.approx(float(spread_of_means), rel=0.05)
    assert summarize(torch.ones(1), "mse", [0.5])["sem"] is None


def test_noisy_support_adds_gaussian_noise_to_the_support_labels_only():
    sigma = 0.3
    collector = SinusoidCollector(n_support=5, n_query=10)
    torch.manual_seed(1)
    tasks = BoxUniform(TaskSpace(["amplitude", "phase"], [0.1, 0.0], [5.0, math.pi])).sample(2000)
    torch.manual_seed(0)
    clean = collector.collect(tasks)
    torch.manual_seed(0)
    noisy = NoisySupport(collector, sigma).collect(tasks)
    assert torch.equal(noisy["support", "x"], clean["support", "x"])
    assert torch.equal(noisy["query", "x"], clean["query", "x"])
    assert torch.equal(noisy["query", "y"], clean["query", "y"])
    noise = (noisy["support", "y"] - clean["support", "y"]).flatten().double()  # 10,000 draws
    assert abs(float(noise.mean())) < 4 * sigma / math.sqrt(noise.numel())
    assert float(noise.std()) == pytest.approx(sigma, rel=0.03)  # 4 standard errors of the std


def test_noisy_support_scores_the_same_tasks_and_points_as_the_clean_evaluation():
    def report(sigma: float) -> dict:
        cfg = compose_train(*SMALL_RUN, "method=maml", f"eval.support_noise={sigma}")
        return evaluate_players(validate(cfg), players_of(cfg))

    faint, strong = report(1e-6), report(3.0)
    assert faint["support_noise"] == 1e-6 and faint["initial_noisy"]["n_tasks"] == 20
    assert faint["initial_noisy"]["mean"] == pytest.approx(faint["initial"]["mean"], rel=1e-4)
    assert strong["initial"] == faint["initial"]
    assert strong["initial_noisy"]["mean"] != pytest.approx(strong["initial"]["mean"], rel=1e-2)
