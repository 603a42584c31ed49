"""armeta-reproduce: every experiment end to end at the tiny profile, each on its first
benchmark (table1's own run is ``tests/test_reproduce.py``'s ``table1_dir``), and the noise sweep
again through the Ray launcher; apart from that file so that the two halves run side by side
under ``pytest -n 2 --dist loadfile``."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

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


ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def noise_dir(tmp_path_factory) -> Path:
    """The noise experiment's tiny sweep, run once for the tests that read it."""
    results = tmp_path_factory.mktemp("noise")
    code = reproduce("noise", "tiny", results, launcher="basic",
                     benchmarks=(FIRST_BENCHMARK["noise"],))
    assert code == 0
    return results


@pytest.mark.parametrize("experiment", sorted(set(FIRST_BENCHMARK) - {"table1"}))
def test_every_experiment_runs_at_tiny_size(tmp_path, request, experiment):
    """(table1 runs in ``tests/test_reproduce.py``'s ``table1_dir`` fixture, noise in
    :func:`noise_dir`, which the Ray sweep's test compares with.)"""
    benchmark = FIRST_BENCHMARK[experiment]
    if experiment == "noise":
        results = request.getfixturevalue("noise_dir")
    else:
        results = tmp_path
        assert reproduce(experiment, "tiny", results, launcher="basic",
                         benchmarks=(benchmark,)) == 0
    plan = make_plan(experiment, "tiny", benchmarks=(benchmark,))
    assert all((results / run.subdir / "eval.json").is_file()
               for run in (*plan.runs, *plan.attacks))
    assert all((results / job.out).is_file() for job in plan.evals)
    assert "complete" in (results / f"{experiment}.md").read_text()
    assert list(results.glob("*.png"))


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


RAY_SWEEP = textwrap.dedent("""
    import sys
    from pathlib import Path
    import ray
    from armeta_rl.reproduce.cli import reproduce

    ray.init(address="local", num_cpus=2, include_dashboard=False)
    try:
        nodes = [node["NodeManagerAddress"] for node in ray.nodes()]
        assert nodes == ["127.0.0.1"], nodes
        code = reproduce("noise", "tiny", Path(sys.argv[1]), launcher="ray",
                         benchmarks=("sinusoid_uniform",))
    finally:
        ray.shutdown()
    sys.exit(code)
""")


def test_a_ray_launched_sweep_equals_the_local_one(tmp_path, noise_dir):
    pytest.importorskip("ray", reason="Ray is not installed: the Ray launcher cannot be tested")
    pytest.importorskip("hydra_plugins.hydra_ray_launcher",
                        reason="hydra-ray-launcher is not installed")
    # Ray serves this machine on 127.0.0.1 only (no other address) when clusters are off.
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1",
           "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "RAY_USAGE_STATS_ENABLED": "0"}
    result = subprocess.run([sys.executable, "-c", RAY_SWEEP, str(tmp_path / "ray")],
                            capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Ray Launcher is launching 5 jobs" in result.stderr + result.stdout
    ray_files = {p.relative_to(tmp_path / "ray"): p for p in (tmp_path / "ray").glob(
        "runs/**/eval*.json")}
    assert len(ray_files) == 10
    for relative, path in ray_files.items():
        ours, theirs = json.loads(path.read_text()), json.loads(
            (noise_dir / relative).read_text())
        for key in ("initial", "initial_noisy", "adversarial", "adversarial_noisy"):
            if key in ours:
                assert ours[key] == theirs[key], (relative, key)
