"""Shift suites (configs/shift_suites/, armeta_rl/tasks/shifts.py): every shift of every suite is
a normalized density on its box whose samples it covers; bad suites, names and boxes are refused
with one line; armeta-eval scores a learner on a suite, the same tasks whatever else it scores."""

import json
import math
import subprocess
import sys

import pytest
import torch

from armeta_rl.cli import evaluate
from armeta_rl.errors import ConfigError
from armeta_rl.job import Job
from armeta_rl.tasks import TaskSpace
from armeta_rl.tasks.shifts import (
    BetaOnBox,
    UniformOnBoxes,
    make_shift,
    shift_seed,
    suite_names,
    suite_shifts,
)
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, compose_train, refusal, train_config

EVAL = [sys.executable, "-c", "from armeta_rl.cli import evaluate; evaluate()"]
BOXES = {
    "point_nav": TaskSpace(["goal_x", "goal_y"], [-0.5, -0.5], [0.5, 0.5]),
    "sinusoid": TaskSpace(["amplitude", "phase"], [0.1, 0.0], [5.0, math.pi]),
    "pendulum": TaskSpace(["m", "l"], [0.4, 0.4], [1.6, 1.6]),
    "half_cheetah_vel": TaskSpace(["goal_velocity"], [0.0], [2.0]),
    "half_cheetah_mass_vel": TaskSpace(["goal_velocity", "mass_scale"], [0.0, 0.75],
                                       [2.0, 1.25]),
    "acrobot": TaskSpace(["m1", "m2"], [0.4, 0.4], [1.6, 1.6]),
    "ant_goal": TaskSpace(["goal_x", "goal_y"], [-3.0, -3.0], [3.0, 3.0]),
}


def test_every_suite_has_its_box_here():
    assert set(BOXES) == set(suite_names())


def test_every_benchmark_with_a_suite_takes_all_of_it():
    from armeta_rl.config import validate
    from armeta_rl.config_files import group_choices
    from armeta_rl.factory import build_space

    with_suite = 0
    for benchmark in group_choices("benchmark"):
        config = validate(compose_train(f"benchmark={benchmark}")).benchmark
        if config.shift_suite is not None:
            with_suite += 1
            assert suite_shifts(build_space(config.space), config.shift_suite, benchmark,
                                "all"), benchmark
    assert with_suite >= len(BOXES)


@pytest.mark.parametrize("suite", sorted(BOXES))
def test_every_shift_is_a_normalized_density_covering_its_samples(suite):
    space = BOXES[suite]
    grid, cell = space.grid(400)
    for name, shift in suite_shifts(space, suite, suite, "all").items():
        torch.manual_seed(0)
        samples = shift.sample_params(20_000)
        assert space.contains(samples).all(), name
        assert torch.isfinite(shift.log_prob(samples)).all(), name
        mass = float(shift.log_prob(grid).exp().sum() * cell)
        # a Beta density with a < 1 is unbounded at the faces, where midpoints miss mass
        assert mass == pytest.approx(1.0, abs=0.05 if isinstance(shift, BetaOnBox) else 1e-6), name


def test_grid_cells_are_equally_likely_and_a_beta_shift_has_its_moments():
    space = BOXES["point_nav"]
    cells = make_shift(space, "c", {"kind": "cells", "grid": [2, 2], "cells": [[0, 0], [1, 1]]})
    torch.manual_seed(1)
    samples = cells.sample_params(40_000)
    low_left = ((samples < 0).all(-1)).double().mean()
    assert float(low_left) == pytest.approx(0.5, abs=0.01)
    assert ((samples < 0).all(-1) | (samples >= 0).all(-1)).all()
    beta = make_shift(space, "b", {"kind": "beta", "a": [2, 5], "b": [5, 2]})
    unit = beta.sample_params(40_000) + 0.5
    assert unit.mean(0).tolist() == pytest.approx([2 / 7, 5 / 7], abs=0.005)
    assert unit.var(0).tolist() == pytest.approx([10 / (49 * 8)] * 2, rel=0.05)
    assert isinstance(cells, UniformOnBoxes) and isinstance(beta, BetaOnBox)


@pytest.mark.parametrize("spec,key,allowed", [
    ({"kind": "box", "low": [-0.6, 0.0], "high": [0.0, 0.5]}, "shifts.s",
     "outside the box: goal_x must stay in [-0.5, 0.5]"),
    ({"kind": "box", "low": [0.0, 0.0], "high": [0.0, 0.5]}, "shifts.s.low", "must be < high"),
    ({"kind": "cells", "grid": [4, 4], "cells": [[4, 0]]}, "shifts.s.cells", "outside the grid"),
    ({"kind": "cells", "grid": [4, 4], "cells": [[1, 1], [1, 1]]}, "shifts.s.cells", "repeats"),
    ({"kind": "beta", "a": [1, 0], "b": [1, 1]}, "shifts.s", "must be > 0"),
    ({"kind": "beta", "a": [1], "b": [1, 1]}, "shifts.s.a", "needs 2 numbers"),
    ({"kind": "ring"}, "shifts.s.kind", "allowed: box, cells, beta"),
    ({"kind": "box", "low": [0, 0]}, "shifts.s", "keys: kind, high, low"),
])
def test_a_malformed_shift_or_one_outside_the_box_is_refused(spec, key, allowed):
    with pytest.raises(ConfigError) as error:
        make_shift(BOXES["point_nav"], "s", spec)
    assert f"'{key}'" in str(error.value) and allowed in str(error.value)


def test_unknown_names_and_suites_are_refused():
    space = BOXES["point_nav"]
    with pytest.raises(ConfigError, match="allowed: all, corner_top_left"):
        suite_shifts(space, "point_nav", "point_nav", ["corner_top_middle"])
    with pytest.raises(ConfigError, match="benchmark.shift_suite"):
        suite_shifts(space, "no_such_suite", "point_nav", "all")
    with pytest.raises(ConfigError, match="has no shift suite"):
        suite_shifts(space, None, "pendulum_gravity", "all")


def test_a_shifts_tasks_depend_on_its_name_only():
    assert shift_seed(1234, "rim") == shift_seed(1234, "rim") != shift_seed(1234, "corner")


@pytest.fixture(scope="module")
def sinusoid_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("shifts") / "maml"
    run_training(Job(train_config(*SMALL_RUN, "method=maml"), run))
    return run


def test_armeta_eval_scores_the_suite_on_the_same_tasks_in_every_report(sinusoid_run):
    def scored(*args):
        result = subprocess.run([*EVAL, f"learner={sinusoid_run}", *args], capture_output=True,
                                text=True, timeout=180)
        assert result.returncode == 0, result.stderr
        return result

    scored("shifts=all")
    every = json.loads((sinusoid_run / "eval_shifts.json").read_text())
    assert [k for k in every if k.startswith("shift/")] == [
        f"shift/{name}" for name in suite_shifts(BOXES["sinusoid"], "sinusoid", "s", "all")]
    assert every["initial"] == json.loads((sinusoid_run / "eval.json").read_text())["initial"]
    scored("shifts=[high_amplitude]", "initial=false", f"out={sinusoid_run / 'one.json'}")
    one = json.loads((sinusoid_run / "one.json").read_text())
    kept = {"metric", "benchmark", "method", "seed", "machine", "config_sha256", "learner",
            "adversary"}
    assert set(one) - kept == {
        "shift/high_amplitude"}
    assert one["shift/high_amplitude"] == every["shift/high_amplitude"]
    assert every["shift/high_amplitude"]["kl_p0"] is None  # a sub-box: KL(p0 ‖ p) is infinite


@pytest.mark.parametrize("args,key,allowed", [
    (["shifts=[corner_top_middle]"], "shifts", "allowed: all, corner_high_amplitude_low_phase"),
    (["shifts=all", "eval.rollouts=0"], "eval.rollouts", "must be >= 1"),
    (["initial=maybe"], "initial", "true or false"),
])
def test_armeta_eval_bad_input_gets_one_line_and_exit_code_2(sinusoid_run, capsys, args, key,
                                                              allowed):
    line = refusal(evaluate, [f"learner={sinusoid_run}", *args], capsys)
    assert f"'{key}'" in line and allowed in line
