"""The one task protocol: every env takes its identifiers under ``TASK_KEY``, keeps
them, and *uses* them, under TorchRL transforms, batched envs, automatic resets and collectors.

Two kinds of checks, each against a reference that does not go through the machinery under test:

* without resets, a transformed (or batched) env's rollout equals the bare env's rollout with the
  same seed, identifiers and actions, and differs from the bare env's rollout with the default
  identifiers (so identifiers that were dropped on the way would be caught);
* across automatic resets (``StepCounter`` truncation in ``env.rollout`` and in
  ``torchrl.collectors.Collector``), every transition is recomputed from its start and action with
  the identifiers that were *given* (analytic reward for the point robot and the MuJoCo task
  families, a fresh bare env reset to the same state for the sys-id envs).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
from torchrl.envs import (
    Compose,
    DoubleToFloat,
    EnvBase,
    ExcludeTransform,
    ObservationNorm,
    ParallelEnv,
    RewardSum,
    SerialEnv,
    StepCounter,
    Transform,
    TransformedEnv,
)

from armeta_rl.envs import (
    AcrobotEnv,
    AntDirEnv,
    AntGoalEnv,
    HalfCheetahDirEnv,
    HalfCheetahVelEnv,
    PendulumEnv,
    PointNavigationEnv,
    Walker2dVelEnv,
)
from armeta_rl.envs.mujoco_tasks import physics_task_env
from armeta_rl.errors import ConfigError, IdentifierError
from armeta_rl.tasks import TASK_KEY
from armeta_rl.tasks.protocol import IdentifierCheck
from conftest import collector_of, compose_train

BATCH = (2, 1)
STEPS = 6


MASS_SCALE = [{"name": "mass_scale", "kind": "body_mass_only_scale", "target": "all",
               "low": 0.75, "high": 1.25}]


@dataclass(frozen=True)
class Case:
    make: Callable[..., EnvBase]  # called with batch_size and seed
    params: tuple[tuple[float, ...], ...]  # one row per task, far from the defaults
    action: tuple[float, ...] | int
    droppable: str  # an output the env's step does not need (for ExcludeTransform)


CASES = {
    "pendulum": Case(PendulumEnv, ((0.5, 1.5), (1.5, 0.5)), (1.0,), "state"),
    "pendulum_f64": Case(partial(PendulumEnv, dtype=torch.float64), ((0.5, 1.5), (1.5, 0.5)),
                         (1.0,), "state"),
    "pendulum_mlg": Case(partial(PendulumEnv, identifiers=("m", "l", "g")),
                         ((0.5, 1.5, 4.0), (1.5, 0.5, 15.0)), (1.0,), "state"),
    "acrobot": Case(AcrobotEnv, ((0.5, 1.5), (1.5, 0.5)), 2, "state"),
    "acrobot_f64": Case(partial(AcrobotEnv, dtype=torch.float64), ((0.5, 1.5), (1.5, 0.5)), 2,
                        "state"),
    "point_nav": Case(PointNavigationEnv, ((0.4, -0.3), (-0.2, 0.45)), (0.05, 0.08),
                      "observation"),
    "ant": Case(partial(AntGoalEnv, threads=1), ((2.0, 1.0), (-1.0, -2.5)), (0.3,) * 8,
                "observation"),
    "ant_dir": Case(AntDirEnv, ((2.0,), (-1.5,)), (0.3,) * 8, "observation"),
    "half_cheetah_vel": Case(HalfCheetahVelEnv, ((0.25,), (1.75,)), (0.3,) * 6, "observation"),
    # directions of the sign opposite to the defaults at seed 0 (+1, +1)
    "half_cheetah_dir": Case(HalfCheetahDirEnv, ((-1.0,), (-0.25,)), (0.3,) * 6, "observation"),
    "walker2d_vel": Case(Walker2dVelEnv, ((0.25,), (1.75,)), (0.3,) * 6, "observation"),
    # MPTS's mass-scale families: (goal_velocity, mass_scale), the mass through the transform
    "half_cheetah_mass_vel": Case(partial(physics_task_env, HalfCheetahVelEnv, MASS_SCALE),
                                  ((0.25, 0.8), (1.75, 1.2)), (0.3,) * 6, "observation"),
    "walker2d_mass_vel": Case(partial(physics_task_env, Walker2dVelEnv, MASS_SCALE),
                              ((0.25, 0.8), (1.75, 1.2)), (0.3,) * 6, "observation"),
}
MUJOCO_FAMILIES = ["ant", "ant_dir", "half_cheetah_vel", "half_cheetah_dir", "walker2d_vel",
                   "half_cheetah_mass_vel", "walker2d_mass_vel"]


def task_td(env: EnvBase, params: torch.Tensor) -> TensorDict:
    """Reset TensorDict giving row ``k`` of ``params [..., K, d]`` to every episode of task k."""
    return TensorDict({TASK_KEY: params.unsqueeze(-2).expand(*env.batch_size, -1)},
                      env.batch_size)


def constant_policy(case: Case, td: TensorDictBase) -> TensorDictBase:
    action = torch.tensor(case.action)
    if action.dtype.is_floating_point:
        action = action.expand(*td.batch_size, -1)
    else:
        action = action.expand(td.batch_size)
    return td.set("action", action)


def rollout(env: EnvBase, case: Case, params: torch.Tensor) -> TensorDictBase:
    return env.rollout(STEPS, partial(constant_policy, case), tensordict=env.reset(
        task_td(env, params)), auto_reset=False, break_when_any_done=False)


def reference(case: Case, params: torch.Tensor) -> TensorDictBase:
    """The bare env's rollout (seed 0) with identifiers ``params`` [K, d]."""
    return rollout(case.make(batch_size=BATCH, seed=0), case, params)


def float64(case: Case) -> bool:
    return getattr(case.make, "keywords", {}).get("dtype") == torch.float64


def transforms(case: Case) -> dict[str, Callable[[], Transform]]:
    made = {
        "compose": Compose,
        "step_counter": partial(StepCounter, max_steps=100),
        "reward_sum": RewardSum,
        "observation_norm": partial(ObservationNorm, loc=0.5, scale=2.0,
                                    in_keys=["observation"], standard_normal=True),
        "exclude": partial(ExcludeTransform, case.droppable),
        "chain": lambda: Compose(StepCounter(100), RewardSum(), ExcludeTransform(case.droppable)),
    }
    if float64(case):
        made["double_to_float"] = DoubleToFloat
    return made


TRANSFORMED = [(name, kind) for name, case in CASES.items() for kind in transforms(case)]


def assert_same_transitions(out: TensorDictBase, ref: TensorDictBase, kind: str) -> None:
    """``out`` (through transform ``kind``) equals the bare env's ``ref`` on reward, params and
    the observation (normalized as ObservationNorm does; in float32 after DoubleToFloat)."""
    expected_obs = ref["next", "observation"]
    if kind == "observation_norm":
        expected_obs = (expected_obs - 0.5) / 2.0
    keys = [("next", "reward"), ("next", TASK_KEY), TASK_KEY]
    for key in keys:
        actual = out[key]
        torch.testing.assert_close(actual, ref[key].to(actual.dtype), rtol=0, atol=0)
    if ("next", "observation") in out.keys(True):
        actual = out["next", "observation"]
        torch.testing.assert_close(actual, expected_obs.to(actual.dtype))


@pytest.mark.parametrize("name", list(CASES))
def test_identifiers_change_the_reference(name):
    """The bare env's rollout with the given identifiers differs from its rollout with the
    defaults, so every equality with the reference below also shows the identifiers were used."""
    case = CASES[name]
    env = case.make(batch_size=BATCH, seed=0)
    default = env.rollout(STEPS, partial(constant_policy, case), auto_reset=True,
                          break_when_any_done=False)
    ref = reference(case, torch.tensor(case.params))
    changed = torch.cat([ref["next", key] != default["next", key]
                         for key in ("observation", "reward")], -1)
    assert changed.flatten(2).any(-1).all()  # in every task and episode


@pytest.mark.parametrize(("name", "kind"), TRANSFORMED)
def test_transformed_env_keeps_and_uses_identifiers(name, kind):
    case = CASES[name]
    params = torch.tensor(case.params)
    env = TransformedEnv(case.make(batch_size=BATCH, seed=0), transforms(case)[kind]())
    given = params.float() if kind == "double_to_float" else params
    assert_same_transitions(rollout(env, case, given), reference(case, params), kind)


def make_step_counted(name: str) -> TransformedEnv:
    """One worker of the batched envs: the env (seed 0) under a StepCounter."""
    return TransformedEnv(CASES[name].make(batch_size=BATCH, seed=0), StepCounter(100))


@pytest.mark.parametrize("batched", ["serial", "parallel"])
@pytest.mark.parametrize("name", ["pendulum", "acrobot", "point_nav", "ant", "half_cheetah_vel"])
def test_batched_transformed_envs_keep_and_use_identifiers(name, batched):
    """Two workers, each a transformed env, given different identifiers through one reset."""
    case = CASES[name]
    params = torch.tensor(case.params)
    given = torch.stack([params, params.flip(0)])  # worker w, task k
    make = partial(make_step_counted, name)
    env = SerialEnv(2, make) if batched == "serial" else ParallelEnv(
        2, make, mp_start_method="fork", num_threads=1, num_sub_threads=1)
    try:
        out = rollout(env, case, given)
    finally:
        env.close()
    ref = torch.stack([reference(case, worker) for worker in given])
    assert_same_transitions(out, ref, "step_counter")


def check_transitions(name: str, data: TensorDictBase, given: torch.Tensor) -> None:
    """Every transition of ``data`` (any batch shape) recomputed with the identifiers ``given``
    (one row per transition, broadcast to ``data``'s batch): the reported identifiers equal them
    and the next state (sys-id) or the reward (point robot, MuJoCo families, from the start and
    next observations) follows from them."""
    data = data.reshape(-1)
    given = given.expand(*data.shape, -1) if given.dim() == 1 else given.reshape(len(data), -1)
    torch.testing.assert_close(data[TASK_KEY], given.to(data[TASK_KEY].dtype), rtol=0, atol=0)
    torch.testing.assert_close(data["next", TASK_KEY], data[TASK_KEY], rtol=0, atol=0)
    if name in ("pendulum", "acrobot"):
        fresh = CASES[name].make(batch_size=(len(data),), seed=1)
        start = fresh.reset(TensorDict({TASK_KEY: given, "state": data["state"]}, [len(data)]),
                            from_state=True)
        expected = fresh.step(start.set("action", data["action"]))["next", "state"]
        torch.testing.assert_close(data["next", "state"], expected)
    elif name == "point_nav":
        distance = (data["next", "observation"] - given).norm(dim=-1, keepdim=True)
        torch.testing.assert_close(data["next", "reward"], -distance)
    elif name == "ant":
        obs = data["next", "observation"]
        reward = (-(obs[..., 116:118] - given).abs().sum(-1)
                  - 5e-3 * data["action"].square().sum(-1)
                  - 5e-4 * obs[..., 29:107].square().sum(-1) + 0.05)
        torch.testing.assert_close(data["next", "reward"].squeeze(-1), reward)
    else:
        torch.testing.assert_close(data["next", "reward"].squeeze(-1),
                                   velocity_reward(name, data, given[:, 0]), rtol=0, atol=2e-4)


def velocity_reward(name: str, data: TensorDictBase, task: torch.Tensor) -> torch.Tensor:
    """The reward of the velocity and direction families, from each transition's start and next
    observation (the torso's position), its action and its task ``[n]`` (the goal velocity or the
    direction; a mass scale changes the dynamics, not the reward)."""
    name = name.replace("_mass_vel", "_vel")
    start, end = data["observation"].double(), data["next", "observation"].double()
    action_cost = data["action"].double().square().sum(-1)
    task = task.double()
    if name == "ant_dir":
        velocity = (end[:, 116:118] - start[:, 116:118]) / 0.05
        along = velocity[:, 0] * task.cos() + velocity[:, 1] * task.sin()
        return (along - 0.5 * action_cost - 5e-4 * end[:, 29:107].square().sum(-1)
                + 1.0).float()
    dt = 0.008 if name == "walker2d_vel" else 0.05
    velocity = (end[:, 17] - start[:, 17]) / dt  # the torso's x, after qpos[1:] and qvel
    if name == "half_cheetah_dir":
        return (torch.where(task >= 0, 1.0, -1.0) * velocity - 0.05 * action_cost).float()
    bonus = 1.0 if name == "walker2d_vel" else 0.0
    return (-(velocity - task).abs() - 0.05 * action_cost + bonus).float()


@pytest.mark.parametrize("name", ["pendulum", "acrobot", "point_nav", *MUJOCO_FAMILIES])
def test_identifiers_survive_automatic_resets_in_rollout_and_collector(name):
    """Episodes truncated every 3 steps by a StepCounter are reset automatically (by
    ``env.rollout`` and by TorchRL's ``Collector``); random actions throughout."""
    torch.manual_seed(0)
    case = CASES[name]
    params = torch.tensor(case.params)
    env = TransformedEnv(case.make(batch_size=BATCH, seed=0), StepCounter(3))
    data = env.rollout(8, tensordict=env.reset(task_td(env, params)),
                       break_when_any_done=False)
    assert data["next", "truncated"].sum() >= 2 * BATCH[0]
    per_task = params[:, None, None].expand(*BATCH, data.shape[-1], -1)
    check_transitions(name, data, per_task)
    collector = Collector(env, None, frames_per_batch=2 * 8, total_frames=2 * 16)
    batches = list(collector)
    collector.shutdown()
    for batch in batches:
        assert batch.shape[:2] == BATCH and batch["next", "truncated"].any()
        check_transitions(name, batch, params[:, None, None].expand(*batch.shape, -1))


BAD_INPUT = [
    # (env, reset entries, the key named in the error, text of what is allowed)
    ("pendulum", {"goal": torch.ones(*BATCH, 2)}, "goal", "go under 'params'"),
    ("pendulum", {"m": torch.ones(*BATCH, 1)}, "m", "go under 'params'"),
    ("pendulum", {TASK_KEY: torch.ones(*BATCH, 3)}, TASK_KEY, "[..., 2]"),
    ("pendulum", {TASK_KEY: torch.tensor([[[1.0, 0.0]], [[1.0, 1.0]]])}, TASK_KEY, "(0, inf)"),
    ("pendulum_mlg", {TASK_KEY: torch.ones(*BATCH, 2)}, TASK_KEY, "(m, l, g)"),
    ("acrobot", {TASK_KEY: torch.full((*BATCH, 2), float("nan"))}, TASK_KEY, "finite"),
    ("point_nav", {"goal": torch.zeros(*BATCH, 2)}, "goal", "go under 'params'"),
    ("point_nav", {TASK_KEY: torch.full((*BATCH, 2), 0.7)}, TASK_KEY, "[-0.5, 0.5]"),
    ("point_nav", {TASK_KEY: torch.zeros(*BATCH, 1)}, TASK_KEY, "(goal_x, goal_y)"),
    ("ant", {"goal": torch.zeros(*BATCH, 2)}, "goal", "go under 'params'"),
    ("ant", {TASK_KEY: torch.full((*BATCH, 2), float("inf"))}, TASK_KEY, "finite"),
    ("ant_dir", {TASK_KEY: torch.zeros(*BATCH, 2)}, TASK_KEY, "(direction_angle)"),
    ("half_cheetah_vel", {"goal_velocity": torch.ones(*BATCH, 1)}, "goal_velocity",
     "go under 'params'"),
    ("half_cheetah_vel", {TASK_KEY: torch.full((*BATCH, 1), float("nan"))}, TASK_KEY, "finite"),
    ("half_cheetah_dir", {TASK_KEY: torch.full((*BATCH, 1), 1.5)}, TASK_KEY, "[-1, 1]"),
    ("walker2d_vel", {"task": torch.ones(*BATCH, 1)}, "task", "go under 'params'"),
    ("half_cheetah_mass_vel", {TASK_KEY: torch.tensor([1.0, 1.5]).expand(*BATCH, 2)}, TASK_KEY,
     "outside the task box (mass_scale in [0.75, 1.25])"),
]


@pytest.mark.parametrize(("name", "entries", "key", "allowed"), BAD_INPUT)
def test_bad_identifiers_raise_one_clear_line(name, entries, key, allowed):
    env = CASES[name].make(batch_size=BATCH, seed=0)
    with pytest.raises(IdentifierError) as error:
        env.reset(TensorDict(entries, BATCH))
    message = str(error.value)
    assert isinstance(error.value, ValueError) and "\n" not in message
    assert message.startswith(f"tensordict key '{key}' = ") and allowed in message


def test_identifiers_that_do_not_broadcast_to_the_batch_raise():
    reset = TensorDict({TASK_KEY: torch.ones(3, 2)}, [])
    with pytest.raises(IdentifierError, match=r"broadcasts to \[2, 1, 2\]"):
        IdentifierCheck.uniform(("m1", "m2"), 0.0, 1.0).read(reset, torch.Size(BATCH))


def test_transformed_reset_forwards_the_task_key_and_the_env_refuses_others():
    """TorchRL's TransformedEnv hands its base env only reset and state-spec keys: the declared
    task key arrives, while an undeclared key such as "goal" is dropped before the env could
    refuse it (a TorchRL limit); the env itself refuses it."""
    env = TransformedEnv(PointNavigationEnv(BATCH, seed=0), StepCounter(10))
    goals = torch.tensor(CASES["point_nav"].params)
    out = env.reset(task_td(env, goals))
    assert torch.equal(out[TASK_KEY], goals[:, None].expand(*BATCH, 2))
    with pytest.raises(IdentifierError):
        env.base_env.reset(TensorDict({"goal": goals[:, None]}, BATCH))


@pytest.mark.parametrize(
    ("overrides", "key", "allowed"),
    [
        (("benchmark=pendulum_uniform", "benchmark.space.names=[mass,l]"),
         "benchmark.space.names", "takes the identifiers ['m', 'l']"),
        (("benchmark=pendulum_uniform", "benchmark.space.low=[0.0,0.4]"),
         "benchmark.space.low", "must be > 0"),
        (("benchmark=acrobot_uniform", "+benchmark.collector.identifiers=[m1,g]"),
         "benchmark.collector.identifiers", "distinct names among m1, m2"),
        (("benchmark=point_nav_plain", "benchmark.space.high=[0.5,0.8]"),
         "benchmark.space", "[-0.5, 0.5]"),
        (("benchmark=half_cheetah_vel", "benchmark.space={names:[v,m],low:[0,0.5],high:[2,1.5]}",
          "benchmark.collector.make_env.threads=1"),
         "benchmark.space", "[..., 1]: 1 value (goal_velocity)"),
    ],
)
def test_a_box_the_env_cannot_take_is_refused_before_training(overrides, key, allowed):
    with pytest.raises(ConfigError) as error:
        collector_of(compose_train(*overrides))
    assert error.value.key == key and allowed in str(error.value)


def test_unknown_identifier_names_are_refused():
    with pytest.raises(ConfigError, match="distinct names among m, l, g"):
        PendulumEnv(identifiers=("m", "length"))
