"""The examples run: the PPO domain-randomization comparison in its quick mode."""

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest
import torch

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
    for source in ("uniform", "adversarial"):
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
    # the same held-out grid for both
    assert results["runs"]["uniform"][0]["eval"]["grid_params"] == \
        results["runs"]["adversarial"][0]["eval"]["grid_params"]
    assert "adversary/grad_norm" in results["runs"]["adversarial"][0]["history"][0]


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
