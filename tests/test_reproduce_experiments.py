"""armeta-reproduce: every experiment end to end at the tiny profile, each on its first
benchmark (table1's own run is ``tests/test_reproduce.py``'s ``table1_dir``); apart from that file
so that the two halves run side by side under ``pytest -n 2 --dist loadfile``."""

import pytest

from armeta_rl.config import validate
from armeta_rl.reproduce.cli import reproduce
from armeta_rl.reproduce.plan import composed, experiment_names, make_plan, run_command

FIRST_BENCHMARK = {
    "table1": "sinusoid_uniform",
    "cnp_table": "sinusoid_uniform",
    "entropy": "sinusoid_uniform",
    "noise": "sinusoid_uniform",
    "point_robot": "point_nav",
    "meta_rl_point": "point_nav",
    "meta_rl_point_validation": "point_nav",
    "meta_rl_cheetah": "half_cheetah_vel",
    "meta_rl_cheetah_mass": "half_cheetah_mass_vel",
    "ant_pos": "ant_goal",
}


@pytest.mark.parametrize("experiment", sorted(set(FIRST_BENCHMARK) - {"table1"}))
def test_every_experiment_runs_at_tiny_size(tmp_path, experiment):
    """(table1 runs in ``tests/test_reproduce.py``'s ``table1_dir`` fixture.)"""
    benchmark = FIRST_BENCHMARK[experiment]
    assert reproduce(experiment, "tiny", tmp_path, launcher="basic", benchmarks=(benchmark,)) == 0
    plan = make_plan(experiment, "tiny", benchmarks=(benchmark,))
    assert all((tmp_path / run.subdir / "eval.json").is_file()
               for run in (*plan.runs, *plan.attacks))
    assert all((tmp_path / job.out).is_file() for job in plan.evals)
    assert "complete" in (tmp_path / f"{experiment}.md").read_text()
    assert list(tmp_path.glob("*.png"))


SETTINGS_VARIANTS = {"meta_rl_cheetah_validation", "meta_rl_cheetah_fair",
                     "meta_rl_cheetah_mass_fair"}
"""Experiments that train meta_rl_cheetah's or meta_rl_cheetah_mass's learners on its benchmark
with other settings (their tiny runs already run the code paths): each of their runs at the
paper profile composes and passes the config check."""


@pytest.mark.parametrize("experiment", sorted(SETTINGS_VARIANTS))
def test_every_run_of_a_settings_variant_composes_and_validates(experiment):
    plan = make_plan(experiment, "paper")
    commands = {run_command(run) for run in (*plan.runs, *plan.attacks)}
    assert len(commands) > 1
    for command in commands:
        validate(composed(command))


def test_every_experiment_is_covered():
    assert set(experiment_names()) == {*FIRST_BENCHMARK, *SETTINGS_VARIANTS, "cvar_curves",
                                       "scatter"}
