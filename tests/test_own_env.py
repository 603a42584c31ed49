"""Bring your own env: a TorchRL env that runs one task per instance, taken
under "params", is meta-trained through one adapter (``one_task_envs``, ``OneTaskEnvCollector``)
and one YAML; shown on TorchRL's pendulum tutorial env, which docs/own-env.md writes out."""

from __future__ import annotations

import ast
import json
import re
from functools import partial
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from armeta_rl.collectors.own_env import one_task_envs
from armeta_rl.envs import tutorial_pendulum
from armeta_rl.envs.tutorial_pendulum import TutorialPendulumEnv
from armeta_rl.errors import ConfigError, IdentifierError
from armeta_rl.job import Job
from armeta_rl.tasks import TASK_KEY
from armeta_rl.trainers.training import run_training
from conftest import train_config

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "own-env.md"
BOX = {"names": ["m", "l"], "low": [0.5, 0.5], "high": [1.5, 1.5]}
TASKS = torch.tensor([[0.5, 1.5], [1.5, 0.5], [1.0, 1.0]])


def check_pendulum_steps(data, tasks: torch.Tensor) -> None:
    """Every transition of ``data`` ``[K, E, T]`` follows the pendulum's equations with its own
    row's task ``tasks[k]`` = (m, l), and reports it."""
    given = tasks[:, None, None].expand(*data.shape, 2)
    assert torch.equal(data[TASK_KEY], given)
    mass, length = given.unbind(-1)
    torque = data["action"].squeeze(-1).clamp(-2.0, 2.0)
    th, thdot = data["th"], data["thdot"]
    expected = (thdot + (3 * 10.0 / (2 * length) * th.sin() + 3.0 / (mass * length**2) * torque)
                * 0.05).clamp(-8.0, 8.0)
    torch.testing.assert_close(data["next", "thdot"], expected)


@pytest.mark.parametrize("instance_batch", [(), (2,)])
def test_the_adapter_runs_each_row_s_task_on_its_instances(instance_batch):
    torch.manual_seed(0)
    env = one_task_envs(partial(TutorialPendulumEnv, batch_size=instance_batch), BOX, (3, 4),
                        max_steps=5)
    assert env.batch_size == (3, 4) and env.task_space.names == ("m", "l")
    start = env.reset(TensorDict({TASK_KEY: TASKS[:, None].expand(3, 4, 2)}, [3, 4]))
    data = env.rollout(5, tensordict=start, auto_reset=False)
    check_pendulum_steps(data, TASKS)
    assert data["next", "truncated"][..., -1, :].all()  # the StepCounter cut the episodes
    env.close()


def test_the_adapter_refuses_in_one_line():
    env = one_task_envs(TutorialPendulumEnv, BOX, (3, 2), max_steps=5)
    for entries, key in (({"param": TASKS[:, None].expand(3, 2, 2)}, "param"),
                         ({TASK_KEY: torch.full((3, 2, 2), 2.0)}, "params")):
        with pytest.raises(IdentifierError, match=f"tensordict key '{key}'") as error:
            env.reset(TensorDict(entries, [3, 2]))
        assert "\n" not in str(error.value)
    with pytest.raises(ConfigError, match="benchmark.collector.episodes.*multiple of 2"):
        one_task_envs(partial(TutorialPendulumEnv, batch_size=(2,)), BOX, (3, 3), max_steps=5)


def swing(tensordict):
    """A fixed policy: full torque one way."""
    return tensordict.set("action", torch.full((*tensordict.batch_size, 1), 2.0))


def test_the_adapter_in_processes_equals_it_in_this_one():
    make = partial(TutorialPendulumEnv, batch_size=(2,))
    runs = []
    for parallel in (False, True):
        env = one_task_envs(make, BOX, (3, 2), max_steps=5, parallel=parallel,
                            mp_start_method="fork")
        env.set_seed(7)
        start = env.reset(TensorDict({TASK_KEY: TASKS[:, None].expand(3, 2, 2)}, [3, 2]))
        runs.append(env.rollout(5, swing, tensordict=start, auto_reset=False))
        env.close()
    check_pendulum_steps(runs[1], TASKS)
    torch.testing.assert_close(runs[0]["next", "observation"], runs[1]["next", "observation"],
                               rtol=0, atol=0)


def test_the_tutorial_benchmark_trains_every_method_kind_and_reports_its_curve(tmp_path):
    config = train_config("benchmark=tutorial_pendulum", "method=ar_maml",
                          "trainer.iterations=2", "trainer.meta_batch=2",
                          "benchmark.collector.max_steps=10", "eval.n_tasks=3",
                          "trainer.progress=false", "logger=none", "trainer.density_every=0")
    report = run_training(Job(config, tmp_path / "run"))
    assert report["adversarial"]["adaptation_curve"]["inner_steps"] == [0, 1, 2, 3]
    assert json.loads((tmp_path / "run" / "eval.json").read_text()) == report


def _code(tree: ast.AST) -> str:
    """The module's code without docstrings."""
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) and isinstance(
                body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
            node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree)


def test_the_page_shows_the_env_and_the_yaml_that_ship():
    page = PAGE.read_text()
    env_block = re.findall(r"```python\n(.*?)```", page, flags=re.S)[0]
    assert _code(ast.parse(env_block)) == _code(ast.parse(Path(tutorial_pendulum.__file__)
                                                          .read_text()))
    yaml_block = re.findall(r"```yaml\n(.*?)```", page, flags=re.S)[0]
    assert yaml_block == (ROOT / "configs" / "benchmark" / "tutorial_pendulum.yaml").read_text()
