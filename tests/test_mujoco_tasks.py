"""PhysicsTaskTransform: identified physics equal a hand-edited MjModel stepped on a raw MjData, the
identifiers survive automatic resets and a Collector, and bad input raises one clear error."""

import os
from functools import partial

import gymnasium
import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import SerialEnv, StepCounter, TransformedEnv
from torchrl.envs.utils import RandomPolicy, check_env_specs

from armeta_rl.config import validate
from armeta_rl.envs.ant_goal import AntGoalEnv, load_ant_model
from armeta_rl.envs.batched_mujoco import load_gym_model
from armeta_rl.envs.mujoco_tasks import (
    PhysicsTaskTransform,
    load_task_family,
    make_gym_task_env,
)
from armeta_rl.errors import ConfigError, IdentifierError
from armeta_rl.job import Job
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, collector_of, compose_train

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CHEETAH_XML = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "mujoco", "assets",
                           "half_cheetah.xml")
CHEETAH = {
    "env": "HalfCheetah-v5",
    "parameters": [
        {"name": "torso_mass", "kind": "body_mass_scale", "target": "torso",
         "low": 0.5, "high": 2.0},
        {"name": "friction", "kind": "geom_friction_scale", "target": "all",
         "low": 0.2, "high": 1.5},
        {"name": "damping", "kind": "joint_damping_scale", "target": "bthigh",
         "low": 0.5, "high": 2.0},
        {"name": "gear", "kind": "actuator_gear_scale", "target": "fthigh",
         "low": 0.5, "high": 2.0},
        {"name": "gravity", "kind": "gravity_z", "low": -12.0, "high": -6.0},
    ],
}
# exactly representable in float32, so the identifiers reach the model unrounded
PARAMS = [1.75, 0.25, 1.5, 0.75, -8.5]


def hand_edited_cheetah(params: list[float]) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """gymnasium's HalfCheetah model with the family's parameters written by hand."""
    model = mujoco.MjModel.from_xml_path(CHEETAH_XML)
    mass, friction, damping, gear, gravity = params
    torso = model.body("torso").id
    model.body_mass[torso] *= mass
    model.body_inertia[torso] *= mass
    model.geom_friction[:, 0] *= friction
    model.dof_damping[model.joint("bthigh").dofadr[0]] *= damping
    model.actuator_gear[model.actuator("fthigh").id, 0] *= gear
    model.opt.gravity[2] = gravity
    data = mujoco.MjData(model)
    mujoco.mj_setConst(model, data)
    return model, data


def step_reference(model: mujoco.MjModel, data: mujoco.MjData, qpos: np.ndarray,
                   qvel: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """HalfCheetah-v5's observations (qpos[1:], qvel) after each action (frame skip 5)."""
    data.qpos[:], data.qvel[:] = qpos, qvel
    observations = []
    for action in actions:
        data.ctrl[:] = action
        mujoco.mj_step(model, data, nstep=5)
        observations.append(np.concatenate([data.qpos[1:], data.qvel]))
    return np.stack(observations)


def test_check_env_specs_single_and_serial():
    family = load_task_family(CHEETAH)
    check_env_specs(make_gym_task_env(family, max_steps=4))
    check_env_specs(make_gym_task_env(family, num_tasks=2, max_steps=4))


def test_gym_dynamics_equal_hand_edited_model():
    """Every observation of the identified GymEnv equals, bit for bit, a raw MjData stepped with
    the hand-edited model from the same state; the nominal model steps elsewhere."""
    torch.manual_seed(0)
    env = make_gym_task_env(load_task_family(CHEETAH))
    env.set_seed(0)
    td = env.reset(TensorDict({"params": torch.tensor(PARAMS)}))
    data = env.base_env._env.unwrapped.data
    qpos, qvel = data.qpos.copy(), data.qvel.copy()
    rollout = env.rollout(40, RandomPolicy(env.action_spec), tensordict=td, auto_reset=False)
    actions = rollout["action"].to(torch.float64).numpy()
    observed = rollout["next", "observation"].numpy()

    expected = step_reference(*hand_edited_cheetah(PARAMS), qpos, qvel, actions)
    np.testing.assert_array_equal(observed, expected)
    nominal = step_reference(*hand_edited_cheetah([1.0, 1.0, 1.0, 1.0, -9.81]), qpos, qvel,
                             actions)
    assert np.abs(nominal - expected).max() > 1e-2
    assert (rollout["params"] == torch.tensor(PARAMS)).all()


def test_nominal_identifiers_leave_the_model_as_compiled():
    env = make_gym_task_env(load_task_family(CHEETAH))
    env.reset(TensorDict({"params": torch.tensor([1.0, 1.0, 1.0, 1.0, -9.81])}))
    model = env.base_env._env.unwrapped.model
    compiled = mujoco.MjModel.from_xml_path(CHEETAH_XML)
    for field in ("body_mass", "body_inertia", "geom_friction", "dof_damping", "actuator_gear",
                  "body_subtreemass", "dof_invweight0"):
        np.testing.assert_allclose(getattr(model, field), getattr(compiled, field), rtol=1e-6)


def test_params_survive_automatic_resets_and_a_collector():
    """Per-sub-env physics stay set through StepCounter truncations inside a Collector; a
    reset without "params" keeps them; a partial reset changes only its sub-env."""
    family = load_task_family(CHEETAH)
    env = make_gym_task_env(family, num_tasks=2, max_steps=3)
    params = torch.tensor([PARAMS, [0.5, 1.5, 2.0, 2.0, -6.0]])
    env.reset(TensorDict({"params": params}, [2]))
    collector = Collector(env, RandomPolicy(env.action_spec), frames_per_batch=16,
                          total_frames=32, auto_register_policy_transforms=False)
    models = [sub._env.unwrapped.model for sub in env.base_env._envs]
    nominal = mujoco.MjModel.from_xml_path(CHEETAH_XML)
    torso = nominal.body("torso").id
    for batch in collector:
        assert batch["next", "done"].sum() >= 4  # automatic resets happened inside the batch
        assert (batch["params"] == params[:, None]).all()
        assert (batch["next", "params"] == params[:, None]).all()
        for model, row in zip(models, params.tolist()):
            assert model.body_mass[torso] == nominal.body_mass[torso] * row[0]
            assert model.opt.gravity[2] == row[4]
    collector.shutdown()
    env.reset()
    assert models[1].body_mass[torso] == nominal.body_mass[torso] * 0.5
    new = params.clone()
    new[1, 0] = 2.0
    reset = torch.tensor([[False], [True]])
    td = env.reset(TensorDict({"params": new, "_reset": reset}, [2]))
    assert models[0].body_mass[torso] == nominal.body_mass[torso] * PARAMS[0]
    assert models[1].body_mass[torso] == nominal.body_mass[torso] * 2.0
    assert (td["params"] == new).all()


def test_ant_goal_env_per_simulation_physics_equal_hand_edited_models():
    """On AntGoalEnv the physics identifiers follow the goal under "params" (one task box of goal
    × physics); each simulation of the [tasks, episodes] batch runs its task's goal and physics,
    equal to a hand-edited MjModel stepped on its own MjData."""
    parameters = [
        {"name": "torso_mass", "kind": "body_mass_scale", "target": "torso", "low": 0.5,
         "high": 2.0},
        {"name": "friction", "kind": "geom_friction_scale", "target": "floor", "low": 0.2,
         "high": 1.5},
        {"name": "gravity", "kind": "gravity_z", "low": -12.0, "high": -6.0},
    ]
    env = TransformedEnv(AntGoalEnv((2, 2), max_steps=10, seed=0),
                         PhysicsTaskTransform(parameters))
    check_env_specs(env)
    assert env.state_spec["params"].shape == (2, 2, 5)
    goals = torch.tensor([[2.0, -1.0], [-0.5, 3.0]])
    physics = torch.tensor([[1.75, 0.25, -6.5], [0.5, 1.5, -11.0]])
    params = torch.cat([goals, physics], -1)[:, None].expand(2, 2, 5)
    td = env.reset(TensorDict({"params": params}, [2, 2]))
    sim = env.base_env.sim
    start = sim.bind("qpos").copy(), sim.bind("qvel").copy()
    torch.manual_seed(0)
    rollout = env.rollout(8, RandomPolicy(env.action_spec), tensordict=td, auto_reset=False)
    actions = rollout["action"].to(torch.float64).reshape(4, 8, -1).numpy()
    for i, (mass, friction, gravity) in enumerate(physics[:, None].expand(2, 2, 3).reshape(4, 3)
                                                  .tolist()):
        model = load_ant_model()
        torso = model.body("torso").id
        model.body_mass[torso] *= mass
        model.body_inertia[torso] *= mass
        model.geom_friction[model.geom("floor").id, 0] *= friction
        model.opt.gravity[2] = gravity
        data = mujoco.MjData(model)
        mujoco.mj_setConst(model, data)
        data.qpos[:], data.qvel[:] = start[0][i], start[1][i]
        for t in range(8):
            data.ctrl[:] = actions[i, t]
            mujoco.mj_step(model, data, nstep=5)
            observed = rollout["next", "observation"].reshape(4, 8, -1)[i, t, :29].numpy()
            expected = np.concatenate([data.qpos, data.qvel]).astype(observed.dtype)
            np.testing.assert_array_equal(observed, expected)
    assert (rollout["params"] == params[:, :, None]).all()
    assert (rollout["next", "params"] == params[:, :, None]).all()
    # the reward's goal term uses the goals, the first two columns (AntGoalEnv's reward)
    obs = rollout["next", "observation"]
    reward = (-(obs[..., 116:118] - goals[:, None, None]).abs().sum(-1)
              - 5e-3 * rollout["action"].square().sum(-1)
              - 5e-4 * obs[..., 29:107].square().sum(-1) + 0.05)
    torch.testing.assert_close(rollout["next", "reward"].squeeze(-1), reward)


def test_shipped_task_families_resolve_on_their_models():
    for name in ("half_cheetah", "hopper"):
        family = load_task_family(os.path.join(ROOT, "configs", "task_family", f"{name}.yaml"))
        env = make_gym_task_env(family)
        low = torch.tensor(family.space.low)
        assert (env.reset(TensorDict({"params": low}))["params"] == low).all()


def test_bad_input_raises_one_clear_error():
    env = make_gym_task_env(load_task_family(CHEETAH))
    with pytest.raises(IdentifierError, match=r"'params' = \[3\.0, .*outside the task box.*"
                                              r"torso_mass in \[0\.5, 2\]"):
        env.reset(TensorDict({"params": torch.tensor([3.0, 1.0, 1.0, 1.0, -9.0])}))
    with pytest.raises(IdentifierError, match=r"'params' = shape \(2,\): a float tensor "
                                              r"\[\.\.\., 5\]: torso_mass, friction"):
        env.reset(TensorDict({"params": torch.tensor([1.0, 1.0])}))
    wrong = {"env": "HalfCheetah-v5", "parameters": [
        {"name": "m", "kind": "body_mass_scale", "target": "no_such_body", "low": 0.5,
         "high": 1.5}]}
    with pytest.raises(ConfigError, match=r"parameters\[0\]\.target' = 'no_such_body'.*"
                                          r"allowed body names: world, torso, bthigh"):
        make_gym_task_env(load_task_family(wrong))
    bad_entries = [
        ({"name": "m", "kind": "mass", "target": "torso", "low": 0.5, "high": 1.5}, "kind"),
        ({"name": "g", "kind": "gravity_z", "target": "torso", "low": -9, "high": -8}, "target"),
        ({"name": "m", "kind": "body_mass_scale", "low": 0.5, "high": 1.5}, "target"),
        ({"name": "m", "kind": "body_mass_scale", "target": "torso", "low": 2, "high": 1}, "low"),
    ]
    for entry, key in bad_entries:
        with pytest.raises(ConfigError, match=rf"parameters\[0\]\.{key}'"):
            load_task_family({"env": "HalfCheetah-v5", "parameters": [entry]})
    overlap = {"env": "HalfCheetah-v5", "parameters": [
        {"name": "floor", "kind": "geom_friction_scale", "target": "floor", "low": 0.5, "high": 1},
        {"name": "all", "kind": "geom_friction_scale", "target": "all", "low": 0.5, "high": 1}]}
    with pytest.raises(ConfigError, match=r"parameters\[1\]\.target' = 'all': .*parameters\[0\] "
                                          r"\(floor\) writes the same geom_friction"):
        make_gym_task_env(load_task_family(overlap))
    twice = [{"name": "m", "kind": "gravity_z", "low": -9, "high": -8}] * 2
    with pytest.raises(ConfigError, match=r"parameters\[1\]\.name' = 'm': names must differ"):
        load_task_family({"env": "HalfCheetah-v5", "parameters": twice})
    with pytest.raises(ConfigError, match="at least one"):
        load_task_family({"env": "HalfCheetah-v5", "parameters": []})
    serial = make_gym_task_env(load_task_family(CHEETAH), num_tasks=2)
    with pytest.raises(IdentifierError, match=r"'params' = shape \(2, 2, 5\): needs \[2, 5\]"):
        serial.reset(TensorDict({"params": torch.tensor([[PARAMS] * 2] * 2)}, [2]))
    stepped = TransformedEnv(make_gym_task_env(load_task_family(CHEETAH)), StepCounter(2))
    with pytest.raises(ValueError, match="outside the task box"):
        stepped.reset(TensorDict({"params": torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0])}))


def test_another_key_and_every_joint():
    """``key`` moves the identifiers to another entry; ``target: all`` scales the damping of
    every degree of freedom of every simulation."""
    parameters = [{"name": "damping", "kind": "joint_damping_scale", "target": "all",
                   "low": 0.5, "high": 2.0}]
    env = TransformedEnv(AntGoalEnv((1, 2), max_steps=5, seed=0),
                         PhysicsTaskTransform(parameters, key="physics"))
    td = env.reset(TensorDict({"physics": torch.full((1, 2, 1), 1.5)}, [1, 2]))
    assert td["params"].shape == (1, 2, 2) and (td["physics"] == 1.5).all()
    nominal = load_ant_model().dof_damping
    damping = env.base_env.sim.expanded("dof_damping")
    np.testing.assert_array_equal(damping, np.broadcast_to(1.5 * nominal, damping.shape))


def test_transform_inside_each_sub_env_of_a_batched_env():
    """The ParallelEnv layout (one transform per worker's env), here in a SerialEnv: the batched
    env forwards each sub-env's row of "params" at reset and keeps it through auto-resets."""
    family = load_task_family(CHEETAH)
    env = SerialEnv(2, partial(make_gym_task_env, family, max_steps=2))
    params = torch.tensor([PARAMS, [0.5, 1.5, 2.0, 2.0, -6.0]])
    td = env.reset(TensorDict({"params": params}, [2]))
    rollout = env.rollout(5, RandomPolicy(env.action_spec), tensordict=td, auto_reset=False,
                          break_when_any_done=False)
    assert rollout["next", "done"].sum() == 4
    assert (rollout["next", "params"] == params[:, None]).all()
    torso = mujoco.MjModel.from_xml_path(CHEETAH_XML).body("torso")
    for sub, row in zip(env._envs, params.tolist()):
        model = sub.base_env._env.unwrapped.model
        assert model.body_mass[torso.id] == torso.mass[0] * row[0]


def test_ant_goal_physics_benchmark_builds_its_env_and_trains(tmp_path):
    """The benchmark YAML's collector runs the [goal, physics] family (its box is 4-D), and
    ar_maml trains on it end to end."""
    cfg = compose_train(*SMALL_RUN, "benchmark=ant_goal_physics", "method=ar_maml",
                        "trainer.iterations=2", "trainer.meta_batch=2", "eval.n_tasks=2",
                        "benchmark.collector.episodes=2", "benchmark.collector.max_steps=10",
                        "benchmark.collector.make_env.threads=1")
    env = collector_of(cfg).env(2)
    params = torch.tensor([[1.0, -2.0, 1.75, 0.5], [0.0, 2.5, 0.5, 1.25]])
    td = env.reset(TensorDict({"params": params[:, None].expand(2, 2, 4)}, [2, 2]))
    assert (td["params"] == params[:, None]).all()
    torso = load_ant_model().body("torso")
    masses = env.base_env.sim.expanded("body_mass")[:, torso.id]
    np.testing.assert_array_equal(masses, torso.mass[0] * np.repeat([1.75, 0.5], 2))
    report = run_training(Job(validate(cfg), tmp_path))
    assert report["metric"] == "return" and "adversarial" in report


@pytest.mark.parametrize("override,match", [
    ("benchmark.space.high=[3,3,2.5,1.5]", r"'benchmark\.space' = .*torso_mass in \[0\.5, 2\]"),
    ("benchmark.space.names=[x,y,m,f]", r"'benchmark\.space' = .*then the physics parameters"),
    ("benchmark.collector.make_env.parameters.0.target=nope",
     r"'benchmark\.collector\.make_env\.parameters\[0\]\.target' = 'nope'"),
])
def test_ant_goal_physics_benchmark_refuses_a_box_or_target_that_does_not_fit(override, match):
    cfg = compose_train("benchmark=ant_goal_physics", "benchmark.collector.episodes=1",
                        "benchmark.collector.make_env.threads=1", override)
    with pytest.raises(ConfigError, match=match):
        collector_of(cfg).env(1)


@pytest.mark.parametrize("benchmark", ["half_cheetah_mass_vel", "walker2d_mass_vel"])
def test_mass_vel_families_equal_hand_scaled_masses_on_raw_mjdata(benchmark):
    """MPTS's MassVel families, built by their benchmark YAMLs: every simulation of a
    [3 tasks, 2 episodes] batch steps as the gymnasium model whose body masses alone (not the
    inertias) are multiplied by its task's mass scale, on its own MjData; its reward follows its
    task's goal velocity; specs hold at several batch shapes."""
    cfg = compose_train(f"benchmark={benchmark}", "benchmark.collector.make_env.threads=1")
    collector = collector_of(cfg)
    for shape in [(1, 1), (3, 2), (4,)]:
        check_env_specs(collector.worker_env(batch_size=shape, max_steps=4, seed=0))
    env = collector.worker_env(batch_size=(3, 2), max_steps=20, seed=0)
    params = torch.tensor([[0.5, 0.75], [1.0, 1.0], [2.0, 1.25]])
    td = env.reset(TensorDict({"params": params[:, None].expand(3, 2, 2)}, [3, 2]))
    base = env.base_env
    start = base.sim.bind("qpos").copy(), base.sim.bind("qvel").copy()
    torch.manual_seed(0)
    rollout = env.rollout(6, RandomPolicy(env.action_spec), tensordict=td, auto_reset=False)
    actions = rollout["action"].double().reshape(6, 6, -1).numpy()
    compiled = load_gym_model(base.xml)
    for i, (velocity, scale) in enumerate(params.repeat_interleave(2, 0).tolist()):
        model = load_gym_model(base.xml)
        model.body_mass[:] *= scale
        data = mujoco.MjData(model)
        mujoco.mj_setConst(model, data)
        np.testing.assert_array_equal(model.body_inertia, compiled.body_inertia)
        data.qpos[:], data.qvel[:] = start[0][i], start[1][i]
        for t in range(6):
            x_before = data.qpos[0]
            data.ctrl[:] = actions[i, t]
            mujoco.mj_step(model, data, nstep=base.frame_skip)
            observed = rollout["next", "observation"].reshape(6, 6, -1)[i, t].double().numpy()
            np.testing.assert_allclose(observed[:8], data.qpos[1:], rtol=1e-6, atol=1e-6)
            reward = rollout["next", "reward"].reshape(6, 6)[i, t].item()
            forward = (data.qpos[0] - x_before) / base.dt
            expected = (-abs(forward - velocity) - 0.05 * np.square(actions[i, t]).sum()
                        + (1.0 if benchmark == "walker2d_mass_vel" else 0.0))
            assert reward == pytest.approx(expected, rel=1e-6, abs=1e-5)
    assert (rollout["params"] == params[:, None, None]).all()
    masses = base.sim.expanded("body_mass")
    scales = np.repeat([0.75, 1.0, 1.25], 2)[:, None]
    np.testing.assert_array_equal(masses, compiled.body_mass * scales)


def test_half_cheetah_mass_vel_benchmark_trains(tmp_path):
    cfg = compose_train(*SMALL_RUN, "benchmark=half_cheetah_mass_vel", "method=ar_maml",
                        "trainer.iterations=2", "trainer.meta_batch=2", "eval.n_tasks=2",
                        "benchmark.collector.episodes=2", "benchmark.collector.max_steps=10",
                        "benchmark.collector.make_env.threads=1")
    report = run_training(Job(validate(cfg), tmp_path))
    assert report["metric"] == "return" and "adversarial" in report
