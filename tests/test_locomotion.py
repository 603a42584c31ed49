"""The planar locomotion families (HalfCheetah-Vel, HalfCheetah-Dir, Walker2d-Vel): TorchRL
contract at several batch shapes, every simulation of a batch against a hand computation on its
own raw MjData with its own task, dynamics and reward against gymnasium's v5 envs, the
half_cheetah_vel benchmark end to end and the docs page's example. Identifiers under transforms,
batched envs and automatic resets: tests/test_task_protocol.py; the mass-scale families:
tests/test_mujoco_tasks.py."""

from __future__ import annotations

import os
import re
from pathlib import Path

import gymnasium
import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs, step_mdp

from armeta_rl.config import validate
from armeta_rl.envs.ant_goal import AntGoalEnv
from armeta_rl.envs.batched_mujoco import GYM_ASSETS, STAGE_POS, load_gym_model
from armeta_rl.envs.locomotion import (
    AntDirEnv,
    HalfCheetahDirEnv,
    HalfCheetahVelEnv,
    Walker2dVelEnv,
    constant_speed_goal_term,
)
from armeta_rl.envs.mujoco_tasks import physics_task_env
from armeta_rl.errors import ConfigError
from armeta_rl.job import Job
from armeta_rl.rl.policy import GaussianActor, GaussianMLP
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, collector_of, compose_train, moved_players, raw_mjdata

ENVS = {"half_cheetah_vel": HalfCheetahVelEnv, "half_cheetah_dir": HalfCheetahDirEnv,
        "walker2d_vel": Walker2dVelEnv}
# one identifier per task of a [4, 2] batch; the directions cover both signs and the boundary 0
TASKS = {"half_cheetah_vel": [0.0, 0.5, 1.25, 2.0], "half_cheetah_dir": [-1.0, -0.25, 0.0, 0.75],
         "walker2d_vel": [0.0, 0.5, 1.25, 2.0]}


def hand_reward(name: str, task: float, x_before: float, data: mujoco.MjData,
                action: np.ndarray, dt: float) -> tuple[float, float]:
    """The family's reward and its forward term (the references' ``reward_forward``) written
    out from the references (module docstring)."""
    velocity = (data.qpos[0] - x_before) / dt
    cost = 0.05 * float(np.sum(action**2))
    if name == "half_cheetah_dir":
        forward = (1.0 if task >= 0 else -1.0) * velocity
        return forward - cost, forward
    bonus = 1.0 if name == "walker2d_vel" else 0.0
    return -abs(velocity - task) - cost + bonus, -abs(velocity - task)


def test_gym_model_is_the_xml_compiled_to_the_bit_without_the_settotalmass_warning(capfd):
    compiled = mujoco.MjModel.from_xml_path(os.path.join(GYM_ASSETS, "half_cheetah.xml"))
    capfd.readouterr()
    model = load_gym_model("half_cheetah.xml")
    assert "settotalmass" not in capfd.readouterr().err
    fields = [name for name in dir(compiled) if not name.startswith("_")]
    compared = 0
    for name in fields:
        value = getattr(compiled, name)
        if isinstance(value, np.ndarray) and value.dtype.kind == "f":
            np.testing.assert_array_equal(getattr(model, name), value, err_msg=name)
            compared += 1
    assert compared > 50 and model.body_mass.sum() == pytest.approx(14.0)


@pytest.mark.parametrize("shape", [(1, 1), (3, 2), (4,), (2, 2, 2)])
@pytest.mark.parametrize("name", list(ENVS))
def test_check_env_specs(name, shape):
    check_env_specs(ENVS[name](shape, max_steps=4, seed=0))


@pytest.mark.parametrize("name", list(ENVS))
def test_every_simulation_equals_a_hand_computation_with_its_own_task(name):
    """Each simulation of a [4 tasks, 2 episodes] batch equals ``mj_step × frame_skip`` then
    ``mj_kinematics`` on its own MjData of the plain gymnasium model, with the observation and
    reward written out by hand from its own task's identifier: the batched env equals a per-task
    reference, through the resets that truncation makes."""
    torch.manual_seed(0)
    env = ENVS[name]((4, 2), max_steps=12, seed=1)
    tasks = torch.tensor(TASKS[name])
    td = env.reset(TensorDict({"params": tasks[:, None, None].expand(4, 2, 1)}, [4, 2]))
    model = load_gym_model(env.xml)
    frame_skip, dt = env.frame_skip, env.frame_skip * model.opt.timestep
    torso = model.body("torso").id
    datas = raw_mjdata(model, env.sim)
    per_sim = tasks.repeat_interleave(2).tolist()
    clip = 10.0 if name == "walker2d_vel" else np.inf
    for step in range(12):
        action = 1.2 * (2 * torch.rand(4, 2, 6) - 1)  # beyond the control range: MuJoCo clamps
        td["action"] = action
        td = env.step(td)
        for i, data in enumerate(datas):
            a = action.reshape(8, 6)[i].double().numpy()
            x_before = data.qpos[0]
            data.ctrl[:] = a
            mujoco.mj_step(model, data, nstep=frame_skip)
            mujoco.mj_kinematics(model, data)
            expected_obs = np.concatenate(
                [data.qpos[1:], np.clip(data.qvel, -clip, clip), data.xpos[torso]])
            obs = td["next", "observation"].reshape(8, -1)[i].double().numpy()
            np.testing.assert_allclose(obs, expected_obs, rtol=1e-6, atol=1e-6)
            reward = td["next", "reward"].reshape(8)[i].item()
            forward = td["next", "reward_forward"].reshape(8)[i].item()
            expected, expected_forward = hand_reward(name, per_sim[i], x_before, data, a, dt)
            assert reward == pytest.approx(expected, rel=1e-6, abs=1e-5)
            assert forward == pytest.approx(expected_forward, rel=1e-6, abs=1e-5)
        assert not td["next", "terminated"].any()
        assert td["next", "truncated"].all() == (step == 11)
        td = step_mdp(td)
    assert (td["params"] == tasks[:, None, None]).all()


@pytest.mark.parametrize("make_env", [
    lambda: HalfCheetahVelEnv((4, 3), max_steps=25, seed=3),
    lambda: Walker2dVelEnv((4, 3), max_steps=25, seed=3),
    lambda: physics_task_env(Walker2dVelEnv, [MASS_SCALE], batch_size=(4, 3), max_steps=25,
                             seed=3),
], ids=["half_cheetah_vel", "walker2d_vel", "walker2d_mass_vel"])
def test_the_torso_position_is_mujocos_forward_kinematics_bit_for_bit(make_env):
    """The torso position the observation carries, computed from the root sliders' qpos with no
    kinematics pass after a step, is MuJoCo's forward kinematics of the batch at the same state
    (``mj_kinematics``, through the batch's ``forward``) bit for bit, at every step of random
    actions beyond the control range (the walkers fall) and through the resets of truncation."""
    torch.manual_seed(0)
    env = make_env()
    runner = getattr(env, "base_env", env)
    xpos = runner.sim.bind("xpos")
    td = env.reset()
    heights = []
    for _ in range(60):
        td["action"] = 3 * (2 * torch.rand(*env.batch_size, 6) - 1)
        _, td = env.step_and_maybe_reset(td)
        computed = runner._torso_position().copy()
        runner.sim.forward(stage=STAGE_POS)
        assert np.array_equal(computed, xpos[:, runner._torso])
        heights.append(computed[:, 2])
    assert np.ptp(np.concatenate(heights)) > 0.3  # the torsos rose and fell, not one pose


@pytest.mark.parametrize(("name", "gym_id"), [("half_cheetah_dir", "HalfCheetah-v5"),
                                              ("walker2d_vel", "Walker2d-v5")])
def test_dynamics_equal_gymnasium_v5(name, gym_id):
    """From the same state and actions, qpos and qvel follow gymnasium's env exactly, and
    HalfCheetah-Dir forward (direction +1) with gymnasium's control weight 0.1 has
    HalfCheetah-v5's reward."""
    torch.manual_seed(0)
    env = ENVS[name]((1, 1), seed=2, ctrl_cost_weight=0.1)
    td = env.reset(TensorDict({"params": torch.ones(1, 1, 1)}, [1, 1]))
    kwargs = {} if name == "half_cheetah_dir" else {"terminate_when_unhealthy": False}
    gym_env = gymnasium.make(gym_id, exclude_current_positions_from_observation=False, **kwargs)
    gym_env.reset(seed=0)
    gym_env.unwrapped.set_state(env.sim.bind("qpos")[0].copy(), env.sim.bind("qvel")[0].copy())
    for _ in range(40):
        action = 2 * torch.rand(1, 1, 6) - 1
        td["action"] = action
        td = env.step(td)
        gym_obs, gym_reward, *_ = gym_env.step(action.reshape(6).double().numpy())
        np.testing.assert_array_equal(env.sim.bind("qpos")[0], gym_obs[:9])
        if name == "half_cheetah_dir":
            np.testing.assert_array_equal(env.sim.bind("qvel")[0], gym_obs[9:])
            assert td["next", "reward"].item() == pytest.approx(gym_reward, rel=1e-6, abs=1e-6)
        else:  # gymnasium's Walker2d observes qvel clipped to ±10, as this env
            np.testing.assert_array_equal(np.clip(env.sim.bind("qvel")[0], -10, 10), gym_obs[9:])
        td = step_mdp(td)
    gym_env.close()


def test_seeded_resets_and_native_threads_change_nothing():
    def run(seed: int, threads: int | None = 1) -> torch.Tensor:
        torch.manual_seed(0)
        env = HalfCheetahVelEnv((2, 3), max_steps=4, seed=seed, threads=threads)
        td, observations = env.reset(), []
        for _ in range(10):
            td["action"] = 2 * torch.rand(2, 3, 6) - 1
            td = env.step_and_maybe_reset(td)[1]
            observations.append(td["observation"])
        return torch.stack(observations)

    assert torch.equal(run(5), run(5))
    assert not torch.allclose(run(5), run(6))
    assert torch.equal(run(5, threads=2), run(5))


MASS_SCALE = {"name": "mass_scale", "kind": "body_mass_only_scale", "target": "all",
              "low": 0.75, "high": 1.25}


def gaussian_rollouts(make_env, per_task: bool, fast: bool, steps: int = 12) -> list:
    """A seeded env of 3 tasks × 2 episodes reset on its tasks and rolled out ``steps`` steps by a
    Gaussian policy (shared or per-task parameters), by ``env.rollout`` or by the env's
    ``gaussian_transitions``; with the simulations' state, step counts and torch's RNG stream
    after it."""
    torch.manual_seed(0)
    env = make_env()
    width = env.observation_spec["params"].shape[-1]
    tasks = (0.75 + 0.25 * torch.rand(3, 1, width)).expand(3, 2, width)  # in every family's box
    net = GaussianMLP(env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1],
                      (16,))
    with torch.no_grad():  # a scale other than 1, which the log-densities then carry
        net.log_std.copy_(torch.linspace(-0.6, 0.3, net.log_std.numel()))
    params = None
    if per_task:
        params = TensorDict.from_module(net).detach().expand(3).clone()
        params.apply_(lambda p: p + 0.1 * torch.randn_like(p))
    env.set_seed(1)
    start = env.reset(TensorDict({"params": tasks}, [3, 2]))
    rollout = (env.gaussian_transitions(steps, net, params) if fast else
               env.rollout(steps, GaussianActor(net, params), tensordict=start, auto_reset=False,
                           break_when_any_done=False))
    base = getattr(env, "base_env", env)
    return [rollout, torch.as_tensor(base._snapshot(base._qpos)),
            torch.as_tensor(base._snapshot(base._qvel)), base._steps.clone(), torch.rand(2)]


@pytest.mark.parametrize("per_task", [False, True])
@pytest.mark.parametrize("make_env", [
    lambda: HalfCheetahVelEnv((3, 2), max_steps=5, seed=0),
    lambda: HalfCheetahDirEnv((3, 2), max_steps=5, seed=0),
    lambda: Walker2dVelEnv((3, 2), max_steps=5, seed=0),
    # torsos leave a narrow healthy range at different steps: partial resets mid-rollout
    lambda: AntDirEnv((3, 2), max_steps=20, seed=0, healthy_z_range=(0.5, 0.8)),
    lambda: AntGoalEnv((3, 2), max_steps=20, seed=0, healthy_z_range=(0.5, 0.8)),
    lambda: physics_task_env(Walker2dVelEnv, [MASS_SCALE], batch_size=(3, 2), max_steps=5,
                             seed=0),
], ids=["half_cheetah_vel", "half_cheetah_dir", "walker2d_vel", "ant_dir", "ant_goal",
        "walker2d_mass_vel"])
def test_gaussian_transitions_equal_env_rollout_bit_for_bit(make_env, per_task):
    """The collectors' rollout of a batched MuJoCo env (alone, or with a mass scale as a
    ``PhysicsTaskEnv``) is ``env.rollout`` with the same stochastic actor (shared or per-task
    parameters): every key it writes at every step, through the automatic resets of truncated
    (5-step limit in 12 steps) and terminated episodes, the simulations' state, step counts and
    the RNG stream left behind."""
    assert callable(getattr(type(make_env()), "gaussian_transitions", None))
    slow = gaussian_rollouts(make_env, per_task, fast=False)
    fast = gaussian_rollouts(make_env, per_task, fast=True)
    ended = fast[0]["next", "done"][..., :-1, :]
    assert ended.any() and not ended.all()
    for key in fast[0].keys(True, True):
        assert torch.equal(fast[0][key], slow[0][key]), key
    for a, b in zip(fast[1:], slow[1:]):
        assert torch.equal(a, b)


def test_gaussian_transitions_equal_env_rollout_on_mujoco_warp():
    """The same on MuJoCo Warp (warp's CPU device), whose bound arrays are torch tensors."""
    warp = pytest.importorskip("warp", reason="MuJoCo Warp is not installed")
    pytest.importorskip("mujoco_warp", reason="MuJoCo Warp is not installed")
    if "cpu" not in [str(device) for device in warp.get_devices()]:
        pytest.skip("warp has no CPU device here (its LLVM backend, warp-clang, is missing)")
    from armeta_rl.envs.locomotion_warp import HalfCheetahVelWarpEnv

    def make_env():
        return HalfCheetahVelWarpEnv((3, 2), max_steps=5, seed=0, warp_device="cpu")

    slow = gaussian_rollouts(make_env, per_task=True, fast=False)
    fast = gaussian_rollouts(make_env, per_task=True, fast=True)
    for key in fast[0].keys(True, True):
        assert torch.equal(fast[0][key], slow[0][key]), key
    for a, b in zip(fast[1:], slow[1:]):
        assert torch.equal(a, b)


@pytest.mark.parametrize("kwargs", [{"max_steps": 0}, {"frame_skip": 0},
                                    {"ctrl_cost_weight": -1.0}, {"reset_noise_scale": -0.1},
                                    {"threads": 0}])
def test_bad_arguments_raise_one_config_error(kwargs):
    key = next(iter(kwargs))
    with pytest.raises(ConfigError, match=rf"'benchmark\.collector\.{key}' = "):
        HalfCheetahVelEnv((1, 1), **kwargs)


def test_half_cheetah_vel_benchmark_trains(tmp_path):
    """The benchmark's collector steps HalfCheetahVelEnv with the YAML's settings, and ar_maml
    (MAML-TRPO under the adversary) trains on it end to end."""
    cfg = compose_train(*SMALL_RUN, "benchmark=half_cheetah_vel", "method=ar_maml",
                        "trainer.iterations=2", "trainer.meta_batch=2", "eval.n_tasks=2",
                        "benchmark.collector.episodes=2", "benchmark.collector.max_steps=10",
                        "benchmark.collector.make_env.threads=1")
    env = collector_of(cfg).env(2)
    assert isinstance(env, HalfCheetahVelEnv) and env.batch_size == (2, 2)
    assert (env.ctrl_cost_weight, env.frame_skip, env.max_steps) == (0.05, 5, 10)
    config = validate(cfg)
    report = run_training(Job(config, tmp_path))
    assert report["metric"] == "return" and "adversarial" in report
    assert moved_players(config, tmp_path) == {"leader": True, "principle": True}


def test_the_docs_example_runs():
    page = Path(__file__).resolve().parents[1] / "docs" / "meta-rl-families.md"
    blocks = re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S)
    assert blocks
    for block in blocks:
        exec(compile(block, str(page), "exec"), {})


def test_the_blind_constant_speed_by_hand_and_against_a_grid_of_speeds():
    """Targets 0, 1, 2 and 0.5 over 10 steps: the median 0.5 (any speed in [0.5, 1] is as good)
    gives −5, −5, −15 and 0, mean −6.25. On 50 random targets no constant speed of a grid
    over [0, 2] has a better mean goal term than the blind reference."""
    hand = constant_speed_goal_term(torch.tensor([0.0, 1.0, 2.0, 0.5]), 10)
    torch.testing.assert_close(hand, torch.tensor([-5.0, -5.0, -15.0, 0.0], dtype=torch.float64))
    torch.manual_seed(0)
    targets = 2 * torch.rand(50, dtype=torch.float64)
    blind = constant_speed_goal_term(targets, 200).mean()
    speeds = torch.linspace(0, 2, 401, dtype=torch.float64)
    on_grid = (-200 * (speeds[:, None] - targets).abs()).mean(-1)
    assert float(blind) >= float(on_grid.max()) - 1e-9


@pytest.mark.parametrize("benchmark,tasks,alive", [
    ("half_cheetah_vel", [[0.2], [1.0], [1.9]], 0.0),
    ("walker2d_mass_vel", [[0.2, 0.8], [1.0, 1.0], [1.9, 1.2]], 1.0)])
def test_the_goal_term_is_the_return_less_its_goal_independent_parts(benchmark, tasks, alive):
    """The collector's goal references of a velocity family (through the mass transform too):
    the achieved goal term is each episode's return plus its control cost (0.05‖a‖² of the
    episodes' actions) less its alive bonus, averaged over episodes; the blind one the best
    constant speed of the batch; the oracle 0."""
    from armeta_rl.rl.policy import GaussianMLP

    collector = collector_of(compose_train(
        f"benchmark={benchmark}", "benchmark.collector.episodes=2",
        "benchmark.collector.max_steps=10", "benchmark.collector.make_env.threads=1"))
    params = torch.tensor(tasks)
    torch.manual_seed(0)
    episodes = collector.collect(TensorDict({"params": params}, [3]),
                                 policy=GaussianMLP(collector.in_features, 6))
    references = collector.goal_references(params, episodes)
    step_goal = (episodes["reward"].squeeze(-1)
                 + 0.05 * episodes["action"].square().sum(-1) - alive) * episodes["mask"]
    torch.testing.assert_close(references["achieved"], step_goal.sum(-1).mean(-1).double(),
                               atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(references["blind"], constant_speed_goal_term(params[:, 0], 10))
    assert bool((references["oracle"] == 0).all())
