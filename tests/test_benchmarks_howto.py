"""A new benchmark on an existing env is one YAML file (docs/benchmarks_howto.md).

The `_normal` benchmarks inherit their `_uniform` sibling through Hydra's defaults list and state
only what differs; the worked example, pendulum_gravity, is the file the docs show and its data
follow the pendulum's equations with each task's own gravity.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from armeta_rl.tasks import TASK_KEY
from conftest import collector_of, compose_train

ROOT = Path(__file__).resolve().parents[1]
HOWTO = ROOT / "docs" / "benchmarks_howto.md"


def composed(benchmark: str) -> dict:
    return OmegaConf.to_container(compose_train(f"benchmark={benchmark}"), resolve=False)


@pytest.mark.parametrize("family", ["sinusoid", "pendulum", "acrobot"])
def test_normal_benchmark_differs_from_uniform_only_in_name_and_p0(family):
    normal, uniform = composed(f"{family}_normal"), composed(f"{family}_uniform")
    assert normal["benchmark"]["initial"]["kind"] == "normal"
    for config in (normal, uniform):
        del config["benchmark"]["name"], config["benchmark"]["initial"]
    assert normal == uniform


def test_gravity_benchmark_is_pendulum_uniform_on_a_3d_box():
    gravity, uniform = composed("pendulum_gravity"), composed("pendulum_uniform")
    assert gravity["benchmark"]["space"]["names"] == ["m", "l", "g"]
    assert gravity["benchmark"]["collector"].pop("identifiers") == "${benchmark.space.names}"
    assert gravity["benchmark"]["shift_suite"] is None  # the pendulum's suite is on (m, l) alone
    for config in (gravity, uniform):
        del config["benchmark"]["name"], config["benchmark"]["space"]
        del config["benchmark"]["shift_suite"]
    assert gravity == uniform


def test_docs_show_the_shipped_yaml():
    shipped = (ROOT / "configs" / "benchmark" / "pendulum_gravity.yaml").read_text()
    blocks = re.findall(r"```yaml\n(.*?)```", HOWTO.read_text(), flags=re.S)
    assert shipped in blocks


def test_docs_python_example_runs():
    blocks = re.findall(r"```python\n(.*?)```", HOWTO.read_text(), flags=re.S)
    assert blocks
    for block in blocks:
        exec(compile(block, str(HOWTO), "exec"), {})


def test_gravity_family_data_follow_each_tasks_gravity():
    """Every transition of the collected data is the pendulum step with its task's (m, l, g):
    Δθ̇ = clip(θ̇ + (3g / (2l) sin θ + 3 / (m l²) u) dt, ±8) − θ̇ (x = cos θ, sin θ, θ̇, u)."""
    torch.manual_seed(0)
    collector = collector_of(compose_train("benchmark=pendulum_gravity"))
    params = torch.tensor([[0.5, 1.5, 5.0], [1.5, 0.5, 15.0], [1.0, 1.0, 10.0]])
    data = collector.collect({TASK_KEY: params})
    x = torch.cat([data["support", "x"], data["query", "x"]], 1).double()
    y = torch.cat([data["support", "y"], data["query", "y"]], 1).double()
    mass, length, gravity = params.double()[:, None].unbind(-1)
    sin, speed, torque = x[..., 1], x[..., 2], x[..., 3]
    dt = 0.05
    accel = 3 * gravity / (2 * length) * sin + 3 / (mass * length**2) * torque
    expected = (speed + accel * dt).clamp(-8, 8) - speed
    torch.testing.assert_close(y[..., 2], expected, atol=2e-5, rtol=0)
    wrong_gravity = (speed + (accel - 3 * (gravity - 10) / (2 * length) * sin) * dt).clamp(-8, 8)
    assert not torch.allclose(y[..., 2], wrong_gravity - speed, atol=1e-3)
