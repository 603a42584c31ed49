"""Evaluation metrics: CVaR_α on hand-made vectors, the standard errors of the mean and of CVaR
(by hand and against the spread of repeated estimates), paired differences, R rollouts per task,
and the noisy-support (random perturbation) evaluation."""

import math

import pytest
import torch

from armeta_rl.collectors import NoisySupport, SinusoidCollector
from armeta_rl.collectors.episodes import episode_returns
from armeta_rl.config import validate
from armeta_rl.envs.locomotion import constant_speed_goal_term
from armeta_rl.tasks import BoxUniform, TaskSpace
from armeta_rl.tasks.protocol import repeat_tasks
from armeta_rl.trainers.evaluation import (
    ReportInvalid,
    adaptation_gain,
    adapts,
    check_report,
    cvar,
    cvar_influence,
    evaluate_on,
    gap_closed,
    paired_difference,
    quarter_scores,
    standard_error,
    summarize,
)
from armeta_rl.trainers.report import eval_scalars, evaluate_players
from conftest import SMALL_RUN, compose_train, players_of


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
    assert report == {"mean": -2.0, "sem": 1.0, "cvar": {"0.5": -3.0}, "cvar_sem": {"0.5": 2.0},
                      "n_tasks": 2, "rollouts": 1, "rollout_sd": None, "per_task": [-1.0, -3.0]}


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


def test_cvar_standard_error_by_hand():
    # losses 1 … 10, α = 0.5: tail 6 … 10 (k = 5), threshold t = 5 (the worst value outside it),
    # z = 5 + 2·(x − 5)₊ = 5, 5, 5, 5, 5, 7, 9, 11, 13, 15: mean 8 = CVaR, sample variance
    # (5·9 + 1 + 1 + 9 + 25 + 49)/9 = 130/9, so the standard error is √(130/90) = √(13/9).
    losses = torch.arange(1.0, 11.0)
    z = cvar_influence(losses, 0.5)
    assert z.tolist() == [5.0] * 5 + [7.0, 9.0, 11.0, 13.0, 15.0]
    assert summarize(losses, "mse", [0.5])["cvar_sem"]["0.5"] == pytest.approx(math.sqrt(13 / 9))
    # returns: the same numbers mirrored
    assert summarize(losses, "return", [0.5])["cvar_sem"]["0.5"] == pytest.approx(
        math.sqrt(13 / 9))
    # a tail of all n values is the mean: z = x
    assert torch.equal(cvar_influence(losses, 0.01), losses.double())


@pytest.mark.parametrize("alpha", [0.1, 0.5, 0.7, 0.9])
@pytest.mark.parametrize("higher_better", [False, True])
def test_cvar_is_the_mean_of_its_influence_values(alpha, higher_better):
    values = torch.distributions.Gamma(2.0, 0.5).sample((37,))
    assert float(cvar_influence(values, alpha, higher_better).mean()) == pytest.approx(
        cvar(values, alpha, higher_better), rel=1e-12)


@pytest.mark.parametrize("n,alpha", [(100, 0.5), (100, 0.9), (500, 0.5)])
def test_cvar_standard_error_is_the_spread_of_cvar_estimates_over_task_draws(n, alpha):
    torch.manual_seed(0)
    draws = torch.distributions.Gamma(2.0, 0.5).sample((3000, n)).double()
    estimates = torch.tensor([cvar(row, alpha) for row in draws])
    sems = torch.tensor([standard_error(cvar_influence(row, alpha)) for row in draws])
    assert float(sems.mean()) == pytest.approx(float(estimates.std()), rel=0.08)


def test_paired_difference_by_hand():
    first, second = [1.0, 2.0, 3.0, 4.0], [0.0, 2.0, 1.0, 5.0]  # differences 1, 0, 2, −1
    diff = paired_difference(first, second, "return", [0.5])
    assert diff["mean"] == pytest.approx(0.5)
    assert diff["sem"] == pytest.approx(math.sqrt(5 / 3) / 2)  # std of the differences / √4
    assert diff["cvar"]["0.5"] == pytest.approx((1 + 2) / 2 - (0 + 1) / 2)  # lowest halves
    za = cvar_influence(torch.tensor(first), 0.5, True)
    zb = cvar_influence(torch.tensor(second), 0.5, True)
    assert diff["cvar_sem"]["0.5"] == pytest.approx(standard_error(za - zb))
    with pytest.raises(ValueError, match="same tasks"):
        paired_difference(first, second[:3], "return", [0.5])


def point_robot():
    """A small point-robot MAML-TRPO leader, p0 and its evaluation collector."""
    players = players_of(compose_train(
        "benchmark=point_nav", "method=maml", "trainer.meta_batch=2",
        "benchmark.collector.episodes=2", "benchmark.collector.max_steps=8"))
    return players.leader, players.initial, players.eval_collector


def test_a_task_scores_the_mean_of_its_rollouts_collected_in_one_batch():
    """With R rollouts, entry r·n + k of the one batch is task k's r-th rollout; the report's
    task score is the mean over r, its noise rollout_sd the pooled within-task spread."""
    leader, initial, collector = point_robot()
    report = evaluate_on(leader, initial, collector, 6, [0.5], seed=3, rollouts=4)
    torch.manual_seed(3)
    tasks = initial.sample(6)
    batch = repeat_tasks(tasks, 4)
    assert torch.equal(batch["params"].reshape(4, 6, 2), tasks["params"].expand(4, 6, 2))
    with torch.no_grad():
        returns = -leader.evaluate(leader.collect(batch, collector)).double().reshape(4, 6)
    assert report["per_task"] == pytest.approx(returns.mean(0).tolist(), rel=1e-5)
    assert report["rollouts"] == 4 and report["n_tasks"] == 6
    assert report["rollout_sd"] == pytest.approx(float(returns.var(0).mean().sqrt()))
    assert report["rollout_sd"] > 0  # the rollouts of a task are independent draws
    assert report["mean"] == pytest.approx(float(returns.mean()))


def test_adaptation_gain_pairs_each_task_after_averaging_its_rollouts():
    """Losses [R=2, n=3]: task scores before 2, 2, 2 and after 0, 1.5, 2, so the gains are 2,
    0.5 and 0 (a lower loss after adaptation is a gain), paired task by task."""
    before = torch.tensor([[1.0, 2.0, 3.0], [3.0, 2.0, 1.0]])
    after = torch.tensor([[0.0, 2.0, 1.0], [0.0, 1.0, 3.0]])
    mse = adaptation_gain(before, after, "mse")
    assert mse["before"] == pytest.approx(2.0)
    assert mse["gain"] == pytest.approx(2.5 / 3)
    assert mse["gain_sem"] == pytest.approx(standard_error(torch.tensor([2.0, 0.5, 0.0])))
    assert mse["improved"] == 2
    returns = adaptation_gain(before, after, "return")  # the same losses are −returns
    assert returns["before"] == pytest.approx(-2.0)
    assert returns["gain"] == pytest.approx(mse["gain"])
    assert adapts(1.0, 0.49) and not adapts(1.0, 0.5) and not adapts(-3.0, 0.1)
    assert not adapts(5.0, None)  # one task: no standard error, no evidence


def test_meta_rl_evaluation_reports_the_return_before_adaptation_of_the_same_episodes():
    """The report's score before adaptation is the return of the very episodes the inner step
    adapted on, and its gain the paired difference to the adapted return, per task over R."""
    leader, initial, collector = point_robot()
    report = evaluate_on(leader, initial, collector, 6, [0.5], seed=3, rollouts=2)
    torch.manual_seed(3)
    with torch.no_grad():
        batch = leader.collect(repeat_tasks(initial.sample(6), 2), collector)
    before = episode_returns(batch.train).mean(-1).double().reshape(2, 6).mean(0)
    after = -leader.evaluate(batch).double().reshape(2, 6).mean(0)
    adaptation = report["adaptation"]
    assert adaptation["before"] == pytest.approx(float(before.mean()), rel=1e-6)
    assert adaptation["gain"] == pytest.approx(float((after - before).mean()), rel=1e-6)
    assert adaptation["improved"] == int((after > before).sum())
    check_report({"metric": "return", "benchmark": "point_nav", "method": "maml",
                  "initial": report})
    with pytest.raises(ReportInvalid, match="adaptation.improved"):
        check_report({"metric": "return", "benchmark": "point_nav", "method": "maml",
                      "initial": {**report, "adaptation": {**adaptation, "improved": 7}}})
    named = {"metric": "return", "benchmark": "point_nav", "method": "maml", "initial": report}
    check_report({**named, "machine": "x86_64 (AVX2); torch 2.13.0"})
    for machine in ({"cpu": "x"}, 3, "x" * 513):
        with pytest.raises(ReportInvalid, match="'machine' is not a machine's name"):
            check_report({**named, "machine": machine})


def test_regression_reports_no_adaptation_gain():
    players = players_of(compose_train("trainer.meta_batch=2"))
    report = evaluate_on(players.leader, players.initial, players.eval_collector, 4, [0.5],
                         seed=0)
    assert "adaptation" not in report


def test_the_share_of_the_goal_blind_gap_closed_by_hand():
    """Goal terms achieved −1 and −3 against a blind −4 and an oracle 0 on both tasks: the
    adapted policy closes (−2 + 4) / (0 + 4) = half the gap; the influence values
    ((a − b) − ½(o − b)) / 4 are ¼ and −¼, so the standard error is std / √2 = ¼. No gap
    (the blind policy as good as the oracle): no share."""
    share, sem = gap_closed(torch.tensor([-1.0, -3.0]), torch.tensor([-4.0, -4.0]),
                            torch.zeros(2))
    assert share == pytest.approx(0.5) and sem == pytest.approx(0.25)
    assert gap_closed(torch.tensor([-1.0]), torch.zeros(1), torch.zeros(1)) == (None, None)


def test_the_share_of_the_gap_closed_is_undefined_on_a_distribution_concentrated_on_one_goal():
    """HalfCheetah-Vel's goal terms over T = 100 steps for one adapted policy that misses every
    target by 0.3 to 0.4 m/s: on p0 (targets U(0, 2)) the goal is worth about 49 and the share
    is 28 ± 6 %; on targets concentrated within 10⁻⁴ m/s of 1.9 (an adversary's p_φ) the best
    constant speed is the oracle, the gap is 0.0025 and the share would be −14132 ± 1221 (its
    error above 1): undefined. The gap's own standard error is a twelfth of it there (the
    references are exact), so a rule on that error would keep it."""
    generator = torch.Generator().manual_seed(0)
    misses = 0.3 + 0.1 * torch.rand(50, generator=generator, dtype=torch.float64)
    achieved, oracle = -100 * misses, torch.zeros(50, dtype=torch.float64)
    p0 = 2 * torch.rand(50, generator=generator, dtype=torch.float64)
    share, sem = gap_closed(achieved, constant_speed_goal_term(p0, 100), oracle)
    assert 0.25 < share < 0.3 and 0.05 < sem < 0.07
    concentrated = 1.9 + 1e-4 * torch.rand(50, generator=generator, dtype=torch.float64)
    blind = constant_speed_goal_term(concentrated, 100)
    gap = -blind
    assert 0 < float(gap.mean()) < 0.005 and float(gap.mean()) > 5 * standard_error(gap)
    assert gap_closed(achieved, blind, oracle) == (None, None)
    assert gap_closed(achieved[:1], constant_speed_goal_term(p0[:1] + 1, 100) - 1,
                      oracle[:1]) == (None, None)  # one task: no error to judge the gap by


def test_quarter_scores_average_the_tasks_of_each_quarter_by_hand():
    scores = torch.tensor([1.0, 3.0, 5.0, 7.0])
    assert quarter_scores(scores, torch.tensor([0, 0, 3, 2])) == [2.0, None, 7.0, 5.0]


def test_a_point_robot_evaluation_scores_the_goal_blind_gap_of_its_own_episodes():
    """The report's goal section on the point robot: the adapted return is all goal term (its
    mean is the section's), the oracle the full-speed path (minus the reference loss) and the
    blind reference no better than it; each quarter's score the mean of its tasks' scores; and
    the schema refuses a goal section whose blind policy beats the oracle, and quarter masses
    that do not sum to 1."""
    leader, initial, collector = point_robot()
    report = evaluate_on(leader, initial, collector, 8, [0.5], seed=3, rollouts=2)
    goal = report["goal"]
    torch.manual_seed(3)
    tasks = initial.sample(8)
    oracle = -collector.reference_loss(tasks["params"].double())
    assert goal["achieved"] == pytest.approx(report["mean"], rel=1e-6)
    assert goal["oracle"] == pytest.approx(float(oracle.mean()))
    assert goal["blind"] < goal["oracle"]
    assert goal["gap_closed"] == pytest.approx(
        (goal["achieved"] - goal["blind"]) / (goal["oracle"] - goal["blind"]))
    quarters = initial.space.quarter(tasks["params"])
    scores = torch.tensor(report["per_task"], dtype=torch.float64)
    assert report["quarter_scores"] == pytest.approx(
        [float(scores[quarters == q].mean()) if (quarters == q).any() else None
         for q in range(4)], rel=1e-5)
    base = {"metric": "return", "benchmark": "point_nav", "method": "maml"}
    check_report({**base, "initial": report})
    assert eval_scalars({**base, "initial": report})["eval/initial/gap_closed"] == goal[
        "gap_closed"]
    with pytest.raises(ReportInvalid, match="goal.blind"):
        check_report({**base, "initial": {**report, "goal": {**goal, "blind": 1.0}}})
    with pytest.raises(ReportInvalid, match="quarter_mass"):
        check_report({**base, "initial": {**report, "quarter_mass": [0.5, 0.5, 0.5, 0.0]}})


def test_an_evaluation_without_episodes_has_no_goal_section():
    players = players_of(compose_train("trainer.meta_batch=2"))
    report = evaluate_on(players.leader, players.initial, players.eval_collector, 4, [0.5],
                         seed=0)
    assert "goal" not in report and len(report["quarter_scores"]) == 4


def test_every_section_records_its_distributions_mass_in_each_quarter():
    """p0 uniform puts a quarter of its mass on each quarter of the box (within 4 standard
    errors of 4096 draws), and the masses sum to 1, in every section of eval.json."""
    report = evaluate_players(validate(compose_train("trainer.meta_batch=2", "eval.n_tasks=4")),
                              players_of(compose_train("trainer.meta_batch=2")))
    mass = report["initial"]["quarter_mass"]
    assert sum(mass) == pytest.approx(1.0)
    assert all(abs(m - 0.25) < 4 * math.sqrt(0.25 * 0.75 / 4096) for m in mass)
