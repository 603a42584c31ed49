"""AntGoalEnv: TorchRL contract, physics and reward against MuJoCo and gymnasium, goals across
resets, seeding, the multi-process split, and training with the tasks split over processes;
AntDirEnv (the same Ant, another task) against a hand computation."""

from functools import partial

import gymnasium
import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import RewardSum, StepCounter, TransformedEnv
from torchrl.envs.utils import RandomPolicy, check_env_specs, step_mdp

from armeta_rl.collectors.episodes import valid_mask
from armeta_rl.collectors.parallel_episodes import TaskSplitEpisodeCollector
from armeta_rl.config import validate
from armeta_rl.envs.ant_goal import AntGoalEnv, load_ant_model, standing_goal_term
from armeta_rl.envs.locomotion import AntDirEnv
from armeta_rl.errors import ConfigError
from armeta_rl.job import Job
from armeta_rl.rl.policy import GaussianMLP
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, compose_train, moved_players, raw_mjdata

CTRL, CONTACT, SURVIVE = 5e-3, 5e-4, 0.05


def goals_td(env: AntGoalEnv, goals: torch.Tensor) -> TensorDict:
    tasks, episodes = env.batch_size
    return TensorDict({"params": goals[:, None].expand(tasks, episodes, 2)}, env.batch_size)


def reward_from_transition(td: TensorDict) -> torch.Tensor:
    """The AntPos reward recomputed from a transition's action, next observation and goal."""
    obs = td["next", "observation"]
    xy, forces = obs[..., 116:118], obs[..., 29:107]
    return (
        -(xy - td["params"]).abs().sum(-1)
        - CTRL * td["action"].square().sum(-1)
        - CONTACT * forces.square().sum(-1)
        + SURVIVE
    )


def test_check_env_specs():
    check_env_specs(AntGoalEnv((2, 3), max_steps=4, seed=0))


def test_step_equals_direct_mujoco_computation():
    """Each env step equals mj_step × 5, mj_forward and mj_rnePostConstraint on a separate MjData
    of the plain gymnasium model, with observation and reward computed from that MjData."""
    torch.manual_seed(0)
    env = AntGoalEnv((2, 2), seed=1)
    goals = torch.tensor([[2.0, -1.0], [-0.5, 3.0]])
    td = env.reset(goals_td(env, goals))
    model = load_ant_model(with_force_sensor=False)
    torso = model.body("torso").id
    datas = raw_mjdata(model, env.sim)
    flat_goals = goals.repeat_interleave(2, 0).double().numpy()
    max_force = 0.0
    for _ in range(30):
        action = 1.2 * (2 * torch.rand(2, 2, 8) - 1)  # beyond the control range: MuJoCo clamps
        td["action"] = action
        td = env.step(td)
        for i, data in enumerate(datas):
            a = action.reshape(4, 8)[i].double().numpy()
            data.ctrl[:] = a
            mujoco.mj_step(model, data, nstep=5)
            mujoco.mj_forward(model, data)
            mujoco.mj_rnePostConstraint(model, data)
            forces = np.clip(data.cfrc_ext, -1, 1)
            expected_obs = np.concatenate(
                [data.qpos, data.qvel, forces[1:].ravel(), data.xmat[torso], data.xpos[torso]]
            )
            expected_reward = (
                -np.abs(data.xpos[torso, :2] - flat_goals[i]).sum()
                - CTRL * np.square(a).sum()
                - CONTACT * np.square(forces).sum()
                + SURVIVE
            )
            obs = td["next", "observation"].reshape(4, -1)[i].double().numpy()
            reward = td["next", "reward"].reshape(4)[i].item()
            np.testing.assert_allclose(obs, expected_obs, rtol=1e-5, atol=1e-5)
            assert reward == pytest.approx(expected_reward, rel=1e-5, abs=1e-5)
            forward = td["next", "reward_forward"].reshape(4)[i].item()
            expected_forward = -np.abs(data.xpos[torso, :2] - flat_goals[i]).sum()
            assert forward == pytest.approx(expected_forward, rel=1e-5, abs=1e-5)
            height_ok = 0.2 <= data.qpos[2] <= 1.0
            assert td["next", "terminated"].reshape(4)[i].item() == (not height_ok)
            max_force = max(max_force, np.abs(data.cfrc_ext).max())
        td = step_mdp(td)
    assert max_force > 1.0  # contact forces are real (the Ant lands), not zeros


@pytest.mark.parametrize("shape", [(1, 1), (3, 2), (4,)])
def test_ant_dir_check_env_specs(shape):
    check_env_specs(AntDirEnv(shape, max_steps=4, seed=0))


def test_ant_dir_every_simulation_equals_a_hand_computation_with_its_own_direction():
    """Each simulation of a [3 tasks, 2 episodes] AntDirEnv steps as mj_step × 5 on its own
    MjData, and its reward is the references' Ant-Dir reward for its own task's angle: velocity
    along (cos θ, sin θ) − 0.5‖a‖² − 0.0005‖clip(cfrc_ext, −1, 1)‖² + 1, terminating outside
    z ∈ [0, 1]."""
    torch.manual_seed(0)
    env = AntDirEnv((3, 2), seed=1)
    angles = torch.tensor([0.0, 2.0, -2.5])
    td = env.reset(TensorDict({"params": angles[:, None, None].expand(3, 2, 1)}, [3, 2]))
    model = load_ant_model(with_force_sensor=False)
    datas = raw_mjdata(model, env.sim)
    radians = angles.double().numpy()
    directions = np.stack([np.cos(radians), np.sin(radians)], -1).repeat(2, 0)
    for _ in range(15):
        action = 1.2 * (2 * torch.rand(3, 2, 8) - 1)
        td["action"] = action
        td = env.step(td)
        for i, data in enumerate(datas):
            a = action.reshape(6, 8)[i].double().numpy()
            xy_before = data.qpos[:2].copy()
            data.ctrl[:] = a
            mujoco.mj_step(model, data, nstep=5)
            mujoco.mj_forward(model, data)
            mujoco.mj_rnePostConstraint(model, data)
            velocity = (data.qpos[:2] - xy_before) / 0.05
            expected = (directions[i] @ velocity - 0.5 * np.square(a).sum()
                        - 5e-4 * np.square(np.clip(data.cfrc_ext, -1, 1)).sum() + 1.0)
            assert td["next", "reward"].reshape(6)[i].item() == pytest.approx(
                expected, rel=1e-5, abs=1e-4)
            assert td["next", "terminated"].reshape(6)[i].item() == (
                not 0.0 <= data.qpos[2] <= 1.0)
        td = step_mdp(td)
    assert (td["params"] == angles[:, None, None]).all()


def test_dynamics_equal_gymnasium_ant_v5():
    """From the same state and actions, qpos and qvel follow gymnasium's Ant-v5 exactly."""
    torch.manual_seed(0)
    env = AntGoalEnv((1, 1), seed=2)
    td = env.reset()
    gym_env = gymnasium.make("Ant-v5", exclude_current_positions_from_observation=False)
    gym_env.reset(seed=0)
    gym_env.unwrapped.set_state(env.sim.bind("qpos")[0].copy(), env.sim.bind("qvel")[0].copy())
    for _ in range(40):
        action = 2 * torch.rand(1, 1, 8) - 1
        td["action"] = action
        td = env.step(td)
        gym_obs = gym_env.step(action.reshape(8).double().numpy())[0]
        np.testing.assert_allclose(env.sim.bind("qpos")[0], gym_obs[:15], rtol=0, atol=1e-12)
        np.testing.assert_allclose(env.sim.bind("qvel")[0], gym_obs[15:29], rtol=0, atol=1e-12)
        td = step_mdp(td)
    gym_env.close()


def test_goals_survive_automatic_resets_in_rollout():
    env = AntGoalEnv((2, 3), max_steps=5, seed=3)
    goals = torch.tensor([[1.5, -2.0], [-3.0, 0.5]])
    start = env.reset(goals_td(env, goals))
    rollout = env.rollout(
        17, RandomPolicy(env.action_spec), tensordict=start, auto_reset=False,
        break_when_any_done=False,
    )
    expected = goals[:, None, None].expand(2, 3, 17, 2)
    assert torch.equal(rollout["params"], expected)
    assert torch.equal(rollout["next", "params"], expected)
    truncated = rollout["next", "truncated"][0, 0, :, 0]
    assert truncated.nonzero().flatten().tolist() == [4, 9, 14]  # three automatic resets
    reward = rollout["next", "reward"].squeeze(-1)
    torch.testing.assert_close(reward, reward_from_transition(rollout), rtol=1e-5, atol=1e-4)


def test_goals_reach_the_env_through_transforms():
    env = TransformedEnv(AntGoalEnv((2, 1), max_steps=3, seed=5), StepCounter())
    env.append_transform(RewardSum())
    check_env_specs(env)
    goals = torch.tensor([[-2.5, 1.0], [0.0, 2.0]])
    start = env.reset(TensorDict({"params": goals[:, None]}, [2, 1]))
    rollout = env.rollout(7, tensordict=start, auto_reset=False, break_when_any_done=False)
    assert torch.equal(rollout["next", "params"], goals[:, None, None].expand(2, 1, 7, 2))
    assert rollout["next", "step_count"].max() == 3


def test_goals_survive_resets_in_collector():
    env = AntGoalEnv((2, 2), max_steps=4, seed=4)
    goals = torch.tensor([[0.5, 2.5], [-1.0, -1.0]])
    env.reset(goals_td(env, goals))
    collector = Collector(
        env, RandomPolicy(env.action_spec), frames_per_batch=4 * 10, total_frames=4 * 20
    )
    for data in collector:
        assert data.batch_size == torch.Size([2, 2, 10])
        assert torch.equal(data["params"], goals[:, None, None].expand(2, 2, 10, 2))
        assert data["next", "done"].any()
        torch.testing.assert_close(
            data["next", "reward"].squeeze(-1), reward_from_transition(data),
            rtol=1e-5, atol=1e-4,
        )
    collector.shutdown()


def test_seeded_reproducibility_and_native_threads_change_nothing():
    actions = 2 * torch.rand(10, 2, 2, 8) - 1

    def run(seed: int, threads: int | None = 1) -> torch.Tensor:
        env = AntGoalEnv((2, 2), max_steps=4, seed=seed, threads=threads)
        td = env.reset()
        observations = [td["observation"]]
        for action in actions:
            td["action"] = action
            td = env.step_and_maybe_reset(td)[1]
            observations.append(td["observation"])
        return torch.stack(observations)

    assert torch.equal(run(5), run(5))
    assert not torch.allclose(run(5)[0], run(6)[0])
    assert torch.equal(run(5, threads=2), run(5))
    assert torch.equal(run(5, threads=None), run(5))


@pytest.mark.parametrize(
    "kwargs", [{"max_steps": 0}, {"healthy_z_range": (1.0, 0.2)}, {"goal_range": 0.0}]
)
def test_bad_config_raises(kwargs):
    with pytest.raises(ConfigError):
        AntGoalEnv((1, 1), **kwargs)


def test_task_split_collector_equals_per_worker_single_process_envs():
    """Tasks split over 2 processes: worker w's slice equals one AntGoalEnv seeded with the w-th
    seed of TorchRL's chain, replaying the collected actions (through terminations and automatic
    resets); the same split stepped in one process (SerialEnv) gives identical data; the global
    seed fixes everything and the goals, log-probs and mask are those of the rollout."""
    tasks, episodes, steps = 4, 2, 15
    make_env = partial(AntGoalEnv, healthy_z_range=(0.3, 0.7))  # early, staggered terminations
    net = GaussianMLP(119, 8)
    params = TensorDict(dict(net.named_parameters()), []).expand(tasks).clone()
    params["log_std"] = torch.linspace(-1.0, 0.5, tasks)[:, None].expand(tasks, 8).clone()
    goals = TensorDict({"params": torch.tensor([[2.0, 1.0], [-1.0, 0.5], [0.0, -3.0], [3.0, 3.0]])},
                       [tasks])
    collector = TaskSplitEpisodeCollector(make_env, episodes, steps, workers=2)
    serial = TaskSplitEpisodeCollector(make_env, episodes, steps, workers=2, in_process=True)
    runs = []
    for collect, seed in [(collector, 0), (serial, 0), (collector, 0), (collector, 1)]:
        torch.manual_seed(seed)
        runs.append(collect.collect(goals, params, policy=net))
    collector.close()
    data = runs[0]
    for other in runs[1:3]:
        assert (data == other).all()
    assert not torch.allclose(data["observation"], runs[3]["observation"])
    assert data.batch_size == torch.Size([tasks, episodes, steps])
    assert torch.equal(data["params"], goals["params"][:, None, None].expand_as(data["params"]))
    assert torch.equal(data["mask"], valid_mask(data["done"].squeeze(-1)))
    assert not data["mask"].all() and data["terminated"].any()

    torch.manual_seed(0)
    seed = int(torch.randint(0, 2**62, ()))
    for w in range(2):
        env = AntGoalEnv((2, episodes), max_steps=steps, healthy_z_range=(0.3, 0.7), seed=0)
        next_seed = env.set_seed(seed)
        rows = slice(2 * w, 2 * w + 2)
        td = env.reset(goals_td(env, goals["params"][rows]))
        for t in range(steps):
            torch.testing.assert_close(td["observation"], data["observation"][rows, :, t])
            td["action"] = data["action"][rows, :, t]
            td, next_td = env.step_and_maybe_reset(td)
            torch.testing.assert_close(td["next", "reward"], data["reward"][rows, :, t])
            assert torch.equal(td["next", "done"], data["done"][rows, :, t])
            td = next_td
        seed = next_seed
    # task k acted with its own parameters (here: its own log_std) on its rows
    with torch.no_grad():
        loc = net.mean(data["observation"])
    scale = params["log_std"].exp()[:, None, None]
    expected = torch.distributions.Normal(loc, scale).log_prob(data["action"]).sum(-1)
    torch.testing.assert_close(data["log_prob"], expected, rtol=1e-5, atol=1e-4)


def test_task_split_needs_workers_dividing_the_tasks():
    collector = TaskSplitEpisodeCollector(AntGoalEnv, 1, 3, workers=2)
    tasks = TensorDict({"params": torch.zeros(3, 2)}, [3])
    with pytest.raises(ConfigError, match="benchmark.collector.workers"):
        collector.collect(tasks, policy=GaussianMLP(119, 8))
    with pytest.raises(ConfigError):
        TaskSplitEpisodeCollector(AntGoalEnv, workers=0)


@pytest.mark.parametrize("override", ["eval.n_tasks=33", "trainer.meta_batch=7"])
def test_a_split_that_does_not_divide_the_task_counts_fails_before_training(override):
    cfg = compose_train("benchmark=ant_goal_parallel", override)
    key, count = override.split("=")
    with pytest.raises(ConfigError, match=rf"benchmark\.collector\.workers.*{key} = {count}"):
        validate(cfg)


def test_ant_goal_trains_with_tasks_split_over_two_processes(tmp_path):
    cfg = compose_train(
        *SMALL_RUN,
        "benchmark=ant_goal_parallel",
        "method=ar_maml",
        "trainer.iterations=2",
        "trainer.meta_batch=2",
        "eval.n_tasks=2",
        "benchmark.collector.episodes=2",
        "benchmark.collector.max_steps=10",
        "logger=csv",
    )
    assert cfg.benchmark.collector.workers == 2
    config = validate(cfg)
    report = run_training(Job(config, tmp_path))
    assert report["metric"] == "return" and "adversarial" in report
    assert moved_players(config, tmp_path) == {"leader": True, "principle": True}
    for curve in ("return_pre", "return_post"):
        assert (tmp_path / "logs" / "scalars" / "train" / f"{curve}.csv").is_file()


def test_the_blind_standing_point_by_hand_and_the_collectors_references():
    """Goals (0, 0), (2, 0), (0, 4) over 5 steps: the coordinate-wise median (0, 0) gives 0, −10
    and −20 (no other point of a grid does better on average); the Ant collector's references
    are its episodes' summed goal terms, that blind reference and the oracle's 0."""
    goals = torch.tensor([[0.0, 0.0], [2.0, 0.0], [0.0, 4.0]])
    torch.testing.assert_close(standing_goal_term(goals, 5),
                               torch.tensor([0.0, -10.0, -20.0], dtype=torch.float64))
    axis = torch.linspace(-3, 5, 81, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 1, 2)
    assert float((-5 * (grid - goals.double()).abs().sum(-1)).mean(-1).max()) <= -10.0 + 1e-9
    collector = TaskSplitEpisodeCollector(partial(AntGoalEnv, threads=1), episodes=2,
                                          max_steps=6)
    torch.manual_seed(0)
    episodes = collector.collect(TensorDict({"params": goals}, [3]),
                                 policy=GaussianMLP(collector.in_features, 8))
    references = collector.goal_references(goals, episodes)
    summed = (episodes["reward_forward"].squeeze(-1) * episodes["mask"]).sum(-1).mean(-1)
    torch.testing.assert_close(references["achieved"], summed.double())
    torch.testing.assert_close(references["blind"], standing_goal_term(goals, 6))
    assert bool((references["oracle"] == 0).all())
