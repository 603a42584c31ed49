"""armeta-reproduce: every experiment end to end at the tiny profile, each on its first
benchmark (table1's own run is ``tests/test_reproduce.py``'s ``table1_dir``), the learning curves
of one, and the noise sweep again through the Ray launcher; apart from that file so that the two
halves run side by side under ``pytest -n 2 --dist loadfile``."""

import json
import os
import shutil
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


CURVE_LOGS = ("logger=csv", "trainer.iterations=2", "trainer.log_every=1")
"""Two iterations, each logged to CSV: what a learning curve is made of."""


@pytest.fixture(scope="module")
def mass_dir(tmp_path_factory) -> Path:
    """meta_rl_cheetah_mass's tiny sweep with :data:`CURVE_LOGS`, run once for the tests that read
    it (its learners and MPTS-MAML log every curve column there is)."""
    results = tmp_path_factory.mktemp("mass")
    assert reproduce("meta_rl_cheetah_mass", "tiny", results, launcher="basic",
                     extra=CURVE_LOGS) == 0
    return results


SHARED = {"noise": "noise_dir", "meta_rl_cheetah_mass": "mass_dir"}
"""The experiments whose tiny sweep is a fixture other tests read too."""


@pytest.mark.parametrize("experiment", sorted(set(FIRST_BENCHMARK) - {"table1"}))
def test_every_experiment_runs_at_tiny_size(tmp_path, request, experiment):
    """(table1 runs in ``tests/test_reproduce.py``'s ``table1_dir`` fixture, those of
    :data:`SHARED` in theirs.)"""
    benchmark = FIRST_BENCHMARK[experiment]
    if experiment in SHARED:
        results = request.getfixturevalue(SHARED[experiment])
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


def test_learning_curves_hold_every_runs_iterations_and_survive_lost_logs(tmp_path, mass_dir,
                                                                          monkeypatch):
    """With CSV logs, the report's curve file holds one row per run and logged iteration, the
    gain is return after − before (an attack run trains no leader: no returns), the batch's
    spread is MPTS's alone; a run whose logs are gone keeps its rows, the figure is drawn from
    the file's rows and keeps its bytes."""
    from armeta_rl.reproduce import figures
    from armeta_rl.reproduce.curves import curves_path, read_curves

    experiment, results = "meta_rl_cheetah_mass", tmp_path / "results"
    shutil.copytree(mass_dir, results)
    plan = make_plan(experiment, "tiny", CURVE_LOGS)
    rows = read_curves(curves_path(results, experiment))
    assert sorted((r["run"], r["iteration"]) for r in rows) == sorted(
        (run.name, i) for run in (*plan.runs, *plan.attacks) for i in (1, 2))
    for row in rows:
        attack = "-vs-" in row["run"]
        assert (row["return_pre"] is None) == attack
        if not attack:
            assert row["gain"] == pytest.approx(row["return_post"] - row["return_pre"],
                                                abs=1e-4)
        assert (row["adversary_entropy"] is None) == (not row["run"].startswith("ar_maml"))
        assert (row["task_spread"] is None) == (not row["run"].startswith("mpts_maml"))
    figure = (results / f"{experiment}_curves.png").read_bytes()
    assert "## Learning curves" in (results / f"{experiment}.md").read_text()
    shutil.rmtree(results / plan.runs[0].subdir / "logs")
    drawn = []
    draw = figures.learning_curves
    monkeypatch.setattr(figures, "learning_curves",
                        lambda rows, *args: drawn.append(rows) or draw(rows, *args))
    assert reproduce(experiment, "tiny", results, launcher="none", extra=CURVE_LOGS) == 0
    assert drawn == [rows]
    assert read_curves(curves_path(results, experiment)) == rows
    assert (results / f"{experiment}_curves.png").read_bytes() == figure


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


def test_a_sweep_stopped_while_it_scores_says_so_and_continues(tmp_path, noise_dir, capsys,
                                                                monkeypatch):
    """SIGTERM during the evaluations: the scoring in flight stops at once, writing nothing,
    the sweep says its evaluations stopped (no run was in flight) and exits 75; the same
    command then makes the missing report, equal to the one first made."""
    import signal

    from armeta_rl.preemption import PROCESS
    from armeta_rl.trainers import report

    results = tmp_path / "results"
    shutil.copytree(noise_dir, results)
    made = next(results.glob("runs/*/*/*/eval_vs_*.json"))
    first = json.loads(made.read_text())
    made.unlink()
    monkeypatch.setattr(PROCESS, "signal", None)  # the request this test makes ends with it
    score = report.evaluate_runs

    def signalled(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return score(*args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(report, "evaluate_runs", signalled)
        assert reproduce("noise", "tiny", results, launcher="basic",
                         benchmarks=(FIRST_BENCHMARK["noise"],)) == 75
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "armeta-reproduce: stopped by SIGTERM: the evaluations in flight stopped, keeping "
        "nothing; the same command continues the sweep")
    assert not made.exists()
    PROCESS.signal = None
    assert reproduce("noise", "tiny", results, launcher="basic",
                     benchmarks=(FIRST_BENCHMARK["noise"],)) == 0
    again = json.loads(made.read_text())
    for paths in ("learner", "adversary"):  # the copy's directories
        again.pop(paths, None), first.pop(paths, None)
    assert again == first
