"""The paper's system-identification protocol (docs/protocol.md): every transition the
``*_paper`` benchmarks collect is a step of the task's own gymnasium system, each task's data is
one 200-step episode, and the paper's tied-angle output head computes what its listing computes."""

import json

import gymnasium
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from armeta_rl.config import validate
from armeta_rl.errors import ConfigError
from armeta_rl.job import Job
from armeta_rl.learners.maml import MAMLLeader, MamlOptions
from armeta_rl.learners.mlp import TiedAngleHead, make_mlp
from armeta_rl.trainers.evaluation import evaluate_on
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, collector_of, compose_train, players_of

PARAMS = [[0.45, 1.5], [1.0, 1.0], [1.55, 0.6]]


def paper_collection(benchmark: str) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)`` ``[tasks, 200, ·]`` of the tasks ``PARAMS`` from the benchmark's collector."""
    collector = collector_of(compose_train(f"benchmark={benchmark}"))
    torch.manual_seed(0)
    data = collector.collect(TensorDict({"params": torch.tensor(PARAMS)}, [len(PARAMS)]))
    x = torch.cat([data["support", "x"], data["query", "x"]], 1).double().numpy()
    y = torch.cat([data["support", "y"], data["query", "y"]], 1).double().numpy()
    return x, y


def pendulum_reference(params: list[float], point: np.ndarray) -> np.ndarray:
    """gymnasium's Pendulum-v1 with mass and length ``params``, stepped once from the state and
    torque of ``point`` = (cos θ, sin θ, θ̇, u): its next observation."""
    env = gymnasium.make("Pendulum-v1").unwrapped
    env.reset(seed=0)
    env.m, env.l = params
    env.state = np.array([np.arctan2(point[1], point[0]), point[2]])
    return env.step(np.array([point[3]]))[0]


def acrobot_reference(params: list[float], point: np.ndarray) -> np.ndarray:
    """gymnasium's Acrobot-v1 with link masses ``params``, stepped once from the state and torque
    of ``point`` = (cos θ1, sin θ1, cos θ2, sin θ2, θ̇1, θ̇2, u): its next observation."""
    env = gymnasium.make("Acrobot-v1").unwrapped
    env.reset(seed=0)
    env.LINK_MASS_1, env.LINK_MASS_2 = params
    angles = np.arctan2(point[[1, 3]], point[[0, 2]])
    env.state = np.concatenate([angles, point[4:6]])
    return env.step(int(round(point[6])) + 1)[0]


@pytest.mark.parametrize(
    ("benchmark", "reference"),
    [("pendulum_uniform_paper", pendulum_reference), ("acrobot_normal_paper", acrobot_reference)],
)
def test_paper_targets_are_the_next_observation_of_each_tasks_own_system(benchmark, reference):
    x, y = paper_collection(benchmark)
    expected = np.stack([
        np.stack([reference(PARAMS[task], point) for point in x[task]])
        for task in range(len(PARAMS))
    ])
    np.testing.assert_allclose(y, expected, atol=2e-4)
    # A task's data is not another task's: the systems differ at these masses.
    assert np.abs(y[0] - y[2]).max() > 1e-2


def test_paper_pendulum_data_is_one_200_step_episode_per_task():
    x, y = paper_collection("pendulum_uniform_paper")
    for task in range(len(PARAMS)):
        starts = {tuple(point[:3].round(5)) for point in x[task]}
        ends = {tuple(point.round(5)) for point in y[task]}
        # In one episode every next observation but the last is the next point's observation.
        assert len(x[task]) == 200 and len(starts & ends) == 199


def test_tied_angle_head_computes_the_papers_output_from_its_body():
    torch.manual_seed(0)
    for observation_dim in (3, 6):
        head = make_mlp(observation_dim + 1, observation_dim, (16,), head="tied_angle")
        x = torch.randn(5, observation_dim + 1)
        angles = head.body(x)
        k = observation_dim // 3
        assert isinstance(head, TiedAngleHead) and angles.shape == (5, k)
        out = head(x)
        for i in range(k):
            torch.testing.assert_close(out[:, 2 * i], angles[:, i].cos())
            torch.testing.assert_close(out[:, 2 * i + 1], angles[:, i].sin())
            torch.testing.assert_close(out[:, 2 * k + i], angles[:, i])


def test_tied_angle_head_is_refused_where_it_cannot_apply():
    with pytest.raises(ConfigError, match="benchmark.model.head"):
        make_mlp(4, 4, head="tied_angle")
    with pytest.raises(ConfigError, match="benchmark.model.head"):
        make_mlp(4, 3, head="angles")
    with pytest.raises(ConfigError, match="learner.maml.adaptation"):
        MAMLLeader(make_mlp(4, 3, head="tied_angle"), None, MamlOptions(adaptation="low_rank"))
    for overrides in (("benchmark.collector.target=delta",), ("method=cnp",)):
        with pytest.raises(ConfigError, match="benchmark.model.head"):
            players_of(compose_train("benchmark=pendulum_normal_paper", *overrides))


def test_a_short_maml_run_on_the_paper_protocol_lowers_the_query_mse(tmp_path):
    cfg = compose_train(*SMALL_RUN, "benchmark=acrobot_uniform_paper", "method=maml",
                        "trainer.iterations=30", "trainer.checkpoint_every=30",
                        "trainer.meta_batch=8")
    untrained = players_of(cfg)
    assert isinstance(untrained.leader.model, TiedAngleHead)
    before = evaluate_on(untrained.leader, untrained.initial, untrained.eval_collector,
                         cfg.eval.n_tasks, [0.5], cfg.eval.seed)["mean"]
    run_training(Job(validate(cfg), tmp_path))
    assert json.loads((tmp_path / "eval.json").read_text())["initial"]["mean"] < 0.7 * before
