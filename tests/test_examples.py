"""The examples run: the PPO domain-randomization comparison in its quick mode, and the
adversary diagnostics on a tiny finished MAML run."""

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from conftest import compose_train

ROOT = Path(__file__).resolve().parent.parent


def load_example(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_ppo_domain_randomization_quick(tmp_path):
    example = load_example("ppo_domain_randomization")
    assert example.main(["--quick", "--out", str(tmp_path)]) == 0
    results = json.loads((tmp_path / "results.json").read_text())
    assert set(results["runs"]) == {"uniform", "adversarial", "mpts", "pdts"}
    for source in example.SOURCES:
        (run,) = results["runs"][source]
        assert len(run["history"]) == example.QUICK.iterations
        evaluation = run["eval"]
        returns = sorted(evaluation["grid_returns"])
        assert len(returns) == example.QUICK.grid ** 2
        episodes = torch.tensor(evaluation["episode_returns"], dtype=torch.float64)
        assert episodes.shape == (len(returns), example.QUICK.eval_episodes)
        assert torch.allclose(episodes.mean(-1), torch.tensor(evaluation["grid_returns"],
                                                               dtype=torch.float64))
        assert (tmp_path / f"actor_{source}_seed0.pt").exists()
        assert evaluation["worst_cell"] == returns[0]
        assert math.isclose(evaluation["cvar_0.5"], sum(returns[:2]) / 2, rel_tol=1e-12)
        assert math.isclose(evaluation["mean_return"], sum(returns) / len(returns), rel_tol=1e-12)
    # the same held-out grid for all
    grids = {str(results["runs"][source][0]["eval"]["grid_params"]) for source in example.SOURCES}
    assert len(grids) == 1
    assert "adversary/grad_norm" in results["runs"]["adversarial"][0]["history"][0]
    for source in ("mpts", "pdts"):  # the risk model learned from every batch's returns
        assert all("risk/pcc" in step for step in results["runs"][source][0]["history"])


@pytest.mark.parametrize("body", ["no_such_body", None])
def test_ppo_domain_randomization_bad_family_exits_2(tmp_path, capsys, body):
    family = tmp_path / "bad.yaml"
    target = f", target: {body}" if body else ""
    family.write_text("env: HalfCheetah-v5\nparameters:\n"
                      f"  - {{name: m, kind: body_mass_scale{target}, low: 0.5, high: 1.5}}\n")
    example = load_example("ppo_domain_randomization")
    assert example.main(["--quick", "--family", str(family), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "task_family.parameters[0].target" in err[0]


TRAIN = [sys.executable, "-c", "from armeta_rl.cli import train; train()"]
TINY_DIAGNOSTICS = ["--grid", "3", "--episodes", "2", "--batches", "3", "--tasks", "4",
                    "--compare", "uniform", "--minmax", "--minmax-sets", "2",
                    "--minmax-draws", "3"]


@pytest.fixture(scope="module")
def tiny_maml_run(tmp_path_factory):
    """A finished two-iteration MAML run of Pendulum-N, trained through the CLI."""
    run_dir = tmp_path_factory.mktemp("maml_n")
    result = subprocess.run(
        [*TRAIN, "benchmark=pendulum_normal_paper", "method=maml", "trainer.iterations=2",
         "trainer.meta_batch=4", "trainer.checkpoint_every=2", "trainer.density_every=0",
         "trainer.progress=false", "logger=none", "eval.n_tasks=10", "learner.maml.hidden=[16]",
         "benchmark.collector.n_transitions=20", f"hydra.run.dir={run_dir}"],
        capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    return run_dir


def diagnostics_json(tmp_path, name, run_dir, *options):
    example = load_example("adversary_diagnostics")
    out = tmp_path / f"{name}.json"
    assert example.main([str(run_dir), *TINY_DIAGNOSTICS, *options, "--json", str(out)]) == 0
    return json.loads(out.read_text())


def test_adversary_diagnostics_on_a_tiny_maml_run(tmp_path, tiny_maml_run, capsys):
    report = diagnostics_json(tmp_path, "first", tiny_maml_run)
    stdout = capsys.readouterr().out
    grid = report["grid"]
    assert grid["names"] == ["m", "l"] and len(grid["params"]) == 9
    params = torch.tensor(grid["params"], dtype=torch.float64)
    assert params.amin(0).tolist() == [0.4, 0.4] and params.amax(0).tolist() == [1.6, 1.6]
    means = torch.tensor(grid["loss_mean"], dtype=torch.float64)
    lam = report["lam"]
    assert lam == 0.2  # risk.ar.lam of the run's config
    assert list(report["distributions"]) == ["p0 (normal)", "uniform"]
    for name, row in report["distributions"].items():
        weights = torch.tensor(row["weights"], dtype=torch.float64)
        assert math.isclose(weights.sum(), 1.0, rel_tol=1e-12)
        assert math.isclose(row["mean"], float((weights * means).sum()), rel_tol=1e-12)
        assert math.isclose(row["sd_signal"],
                            float((weights * (means - row["mean"]) ** 2).sum().sqrt()),
                            rel_tol=1e-9)
        best = row["maximizer"]
        density = torch.tensor(best["density"], dtype=torch.float64)
        assert math.isclose(density.sum(), 1.0, rel_tol=1e-12) and (density > 0).all()
        assert math.isclose(best["loss_mean"], float((density * means).sum()), rel_tol=1e-12)
        assert best["kl"] >= 0
        # J(p*) >= J(p0): E_p*[L] − E_p0[L] >= λ·KL(p0 ‖ p*)
        assert best["loss_mean"] - row["mean"] >= lam * best["kl"] - 1e-9
        line = next(x for x in stdout.splitlines() if x.startswith(name))
        assert [float(x) for x in line[len(name):].split()] == [
            round(v, 4) for v in (row["mean"], row["sd_signal"], row["sd_noise"],
                                  best["loss_mean"], best["kl"])]
    uniform = torch.tensor(report["distributions"]["uniform"]["weights"])
    assert torch.allclose(uniform, torch.full((9,), 1 / 9, dtype=uniform.dtype))
    gradient = report["gradient"]
    assert gradient["batch_sd"] > 0 and gradient["mean_norm"] >= 0
    assert f"|E g| {gradient['mean_norm']:.4f}, sd of one batch's g " \
           f"{gradient['batch_sd']:.4f}" in stdout
    minmax = report["minmax"]
    assert minmax["tasks_per_set"] == 9
    assert math.isclose(minmax["difference"], minmax["stretched_mean"] - minmax["plain_mean"],
                        abs_tol=1e-12)
    assert minmax["plain_cvar_0.5"] >= minmax["plain_mean"] - 1e-12
    assert f"min–max stretched {minmax['stretched_mean']:.4f}" in stdout
    again = diagnostics_json(tmp_path, "again", tiny_maml_run)
    assert again == report
    other = diagnostics_json(tmp_path, "other", tiny_maml_run, "--seed", "1")
    assert other["grid"]["loss_mean"] != report["grid"]["loss_mean"]


def test_adversary_diagnostics_minmax_stretch_spans_the_box():
    example = load_example("adversary_diagnostics")
    values = torch.tensor([[0.9, 1.1], [1.0, 0.7], [1.2, 1.0]], dtype=torch.float64)
    low, high = torch.tensor([0.4, 0.4]).double(), torch.tensor([1.6, 1.6]).double()
    stretched = example.minmax_stretch(values, low, high)
    assert torch.equal(stretched.amin(0), low) and torch.equal(stretched.amax(0), high)
    assert torch.equal(stretched.argsort(0), values.argsort(0))  # order kept per identifier


@pytest.mark.parametrize("case,words", [
    ("not_a_run", "'run'"),
    ("pendulum_gravity", "3-D"),
    ("point_nav", "regression or system-identification"),
    ("--grid=1", "'--grid' = 1: must be an integer >= 2"),
    ("--compare=normal", "invalid choice: 'normal'"),
])
def test_adversary_diagnostics_bad_input_exits_2(tmp_path, capsys, tiny_maml_run, case, words):
    example = load_example("adversary_diagnostics")
    if case.startswith("--"):
        argv = [str(tiny_maml_run), case]
    else:
        run_dir = tmp_path / case
        run_dir.mkdir()
        if case != "not_a_run":
            OmegaConf.save(compose_train(f"benchmark={case}", "method=maml"),
                           run_dir / "config.yaml")
        argv = [str(run_dir)]
    assert example.main(argv) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and words in err[0] and captured.out == ""


def test_budget_pilot_trains_in_stages_and_reports_each(tmp_path):
    """Two stages of a tiny point-robot MAML run: each is scored on p0 with its adaptation gain,
    the table reads the gains of the stages' reports, and the curve holds every iteration."""
    from armeta_rl.reproduce.curves import read_curves

    example = load_example("budget_pilot")
    run, out = tmp_path / "pilot", tmp_path / "report"
    assert example.main(["--run", str(run), "--out", str(out), "--stages", "1", "2", "--",
                         "benchmark=point_nav", "method=maml", "trainer.meta_batch=2",
                         "benchmark.collector.episodes=2", "benchmark.collector.max_steps=5",
                         "eval.n_tasks=3"]) == 0
    rows = example.stage_rows(run)
    assert [r["iteration"] for r in rows] == [1, 2]
    for row in rows:
        gain = json.loads((run / f"eval_at_{row['iteration']}.json").read_text())
        assert row["gain"] == gain["initial"]["adaptation"]["gain"]
    table = (out / "pilot.md").read_text()
    assert f"{rows[1]['gain']:+.1f} ± {rows[1]['gain_sem']:.1f}" in table
    assert [r["iteration"] for r in read_curves(out / "pilot_curves.csv.gz")] == [1, 2]
    assert (out / "pilot.png").stat().st_size > 0
