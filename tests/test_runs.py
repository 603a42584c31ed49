"""A finished run in one call, and the curve users plot: ``load_run`` gives
the config, the players with the last checkpoint and the checked reports of a run directory;
a meta-RL evaluation reports the return after 0, 1, ..., k inner steps, the first two those of
the same episodes as the report's score before and after adaptation; ``armeta-eval`` prints it
and the reports plot it."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

import armeta_rl
from armeta_rl.cli import evaluate
from armeta_rl.collectors.episodes import episode_returns
from armeta_rl.errors import ConfigError
from armeta_rl.job import Job
from armeta_rl.learners.maml_trpo import as_task_params
from armeta_rl.plots import plot_adaptation_curves
from armeta_rl.trainers.evaluation import (
    ReportInvalid,
    check_report,
    curve_steps,
    evaluate_on,
    format_table,
)
from armeta_rl.trainers.training import run_training
from conftest import in_process, refusal, train_config

RUN = ("benchmark=point_nav_plain", "method=ar_maml", "seed=3", "trainer.iterations=2",
       "trainer.checkpoint_every=2", "trainer.meta_batch=2", "trainer.progress=false",
       "trainer.density_every=0", "logger=none", "benchmark.collector.episodes=2",
       "benchmark.collector.max_steps=8", "eval.n_tasks=4", "eval.rollouts=2")


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A small MAML-TRPO run with an adversary, trained and evaluated."""
    run_dir = tmp_path_factory.mktemp("run") / "run"
    report = run_training(Job(train_config(*RUN), run_dir))
    return run_dir, report


def test_load_run_gives_the_config_players_and_reports(finished):
    run_dir, report = finished
    run = armeta_rl.load_run(run_dir)
    assert run.config.benchmark.name == "point_nav_plain" and run.config.seed == 3
    assert run.reports["eval"] == report
    assert run.adversary is run.players.principle.adversary and run.adversary is not None
    # the loaded leader is the trained one: scoring it again gives the report's numbers
    ev = run.config.eval
    again = evaluate_on(run.leader, run.players.initial, run.players.eval_collector,
                        ev.n_tasks, list(ev.alphas), ev.seed, rollouts=ev.rollouts)
    assert again["mean"] == report["initial"]["mean"]
    assert again["adaptation_curve"] == report["initial"]["adaptation_curve"]


def test_load_run_refuses_in_one_line(tmp_path, finished):
    with pytest.raises(ConfigError, match="'run' = .*is not a run directory"):
        armeta_rl.load_run(tmp_path)
    run_dir, report = finished
    broken = tmp_path / "copy"
    broken.mkdir()
    for file in ("config.yaml",):
        (broken / file).write_text((run_dir / file).read_text())
    (broken / "checkpoints").symlink_to(run_dir / "checkpoints")
    with pytest.raises(ConfigError, match="its checkpoints is a link") as error:
        armeta_rl.load_run(broken)  # a run directory is data: no link is followed
    assert "\n" not in str(error.value)
    (broken / "checkpoints").unlink()
    shutil.copytree(run_dir / "checkpoints", broken / "checkpoints")
    (broken / "eval.json").write_text(json.dumps({**report, "initial": {
        **report["initial"], "mean": 12345.0}}))
    with pytest.raises(ConfigError, match="its report eval.json is invalid") as error:
        armeta_rl.load_run(broken)
    assert "\n" not in str(error.value)


def test_the_curve_starts_at_the_report_s_scores_before_and_after_adaptation(finished):
    _, report = finished
    for section in ("initial", "adversarial"):
        scores = report[section]
        curve = scores["adaptation_curve"]
        assert curve["inner_steps"] == [0, 1, 2, 3]  # MAML-TRPO trains with 1: 1 + 2 by default
        assert curve["mean"][0] == pytest.approx(scores["adaptation"]["before"], rel=1e-12)
        assert curve["mean"][1] == pytest.approx(scores["mean"], rel=1e-12)
        assert all(sem > 0 for sem in curve["sem"])


def test_each_further_point_adapts_the_last_policy_on_its_own_episodes(finished):
    """Replayed by hand on the same random stream: step 2 is one more inner step from the
    adapted policy on the episodes it rolled out, then a rollout of the new policy."""
    players = armeta_rl.load_run(finished[0]).players
    leader, collector = players.leader, players.eval_collector
    report = evaluate_on(leader, players.initial, collector, 3, [0.5], seed=5, adaptation_steps=2)
    torch.manual_seed(5)
    tasks = players.initial.sample(3)
    with torch.no_grad():
        batch = leader.collect(tasks, collector)
    params = leader.further_step(batch.adapted, batch.valid, batch.valid_advantages)
    episodes = collector.collect(tasks, as_task_params(params), policy=leader.net)
    expected = episode_returns(episodes).mean(-1).double().mean()
    assert report["adaptation_curve"]["mean"][2] == pytest.approx(float(expected), rel=1e-12)
    assert report["adaptation_curve"]["mean"][2] != report["adaptation_curve"]["mean"][1]


def test_the_curve_s_length_is_configurable_and_refused_without_inner_steps(finished):
    run = armeta_rl.load_run(finished[0])
    players = run.players
    report = evaluate_on(players.leader, players.initial, players.eval_collector, 3, [0.5],
                         seed=0, adaptation_steps=5)
    assert report["adaptation_curve"]["inner_steps"] == list(range(6))
    regression = train_config("trainer.meta_batch=2", "eval.adaptation_steps=3")
    with pytest.raises(ConfigError, match="eval.adaptation_steps"):
        run_training(Job(regression, finished[0].parent / "regression"))
    assert curve_steps(players.leader, None) == 3


def test_a_report_with_a_broken_curve_is_refused(finished):
    _, report = finished
    curve = report["initial"]["adaptation_curve"]
    check_report(report)
    for broken in ({**curve, "mean": curve["mean"][:-1]}, {**curve, "inner_steps": [1, 2]},
                   {**curve, "sem": [None] * len(curve["sem"])}):
        with pytest.raises(ReportInvalid, match="adaptation_curve"):
            check_report({**report, "initial": {**report["initial"], "adaptation_curve": broken}})


def test_armeta_eval_prints_the_curve_and_the_reports_plot_it(finished, capsys, tmp_path):
    run_dir, report = finished
    out = tmp_path / "again.json"
    code, printed, err = in_process(evaluate, [f"learner={run_dir}", "eval.adaptation_steps=4",
                                               f"out={out}"], capsys)
    assert code == 0, err
    again = json.loads(out.read_text())
    assert again["initial"]["adaptation_curve"]["inner_steps"] == [0, 1, 2, 3, 4]
    assert "return after 0..4 inner steps" in printed
    assert format_table(again).splitlines()[-1].startswith("adversarial")
    figure = plot_adaptation_curves({"trained": report, "again": again}, tmp_path / "c.png")
    lines = figure.axes[0].get_lines()
    assert [list(line.get_ydata()) for line in lines] == [
        report["initial"]["adaptation_curve"]["mean"], again["initial"]["adaptation_curve"]["mean"]]
    assert (tmp_path / "c.png").stat().st_size > 0
    with pytest.raises(ConfigError, match="no adaptation curve"):
        plot_adaptation_curves({"regression": {"initial": {"mean": 1.0}}}, tmp_path / "d.png")


def test_armeta_eval_refuses_a_curve_length_below_one(finished, capsys):
    line = refusal(evaluate, [f"learner={finished[0]}", "eval.adaptation_steps=0"], capsys)
    assert "eval.adaptation_steps" in line and ">= 1" in line


def test_the_loaded_players_compute_on_the_device_asked(finished):
    run = armeta_rl.load_run(finished[0], device="cpu")
    assert next(run.leader.net.parameters()).device == torch.device("cpu")
