"""Every env the package builds tells its whole task box and p0: the base envs,
the physics families (MassVel on CPU MuJoCo and on MuJoCo Warp), a gymnasium env's family, the
wrappers a user puts around them and the batched envs; ``TaskTransform(env.p0)`` then draws
tasks the env takes. Every benchmark's env tells the box its YAML trains on."""

from __future__ import annotations

from functools import partial
from pathlib import Path

import pytest
import torch
from torchrl.envs import Compose, ParallelEnv, StepCounter, TransformedEnv

from armeta_rl.collectors.episodes import EpisodeCollector
from armeta_rl.config import validate
from armeta_rl.envs import (
    AcrobotEnv,
    AntDirEnv,
    AntGoalEnv,
    HalfCheetahDirEnv,
    HalfCheetahVelEnv,
    PendulumEnv,
    PointNavigationEnv,
    TaskParallelEnv,
    TaskSerialEnv,
    Walker2dVelEnv,
    task_space,
)
from armeta_rl.envs.mujoco_tasks import load_task_family, make_gym_task_env, physics_task_env
from armeta_rl.errors import ConfigError
from armeta_rl.factory import build_space
from armeta_rl.tasks import TASK_KEY, BoxUniform, TaskSpace, TaskTransform
from conftest import collector_of, compose_train

BENCHMARKS = sorted(p.stem for p in (Path(__file__).parents[1] / "configs" / "benchmark").glob(
    "*.yaml"))
MASS = [{"name": "mass_scale", "kind": "body_mass_only_scale", "target": "all", "low": 0.75,
         "high": 1.25}]
POLE = {"env": "InvertedPendulum-v5", "parameters": [
    {"name": "pole_mass", "kind": "body_mass_scale", "target": "pole", "low": 0.5, "high": 2.0}]}
VELOCITY = TaskSpace(["goal_velocity", "mass_scale"], [0.0, 0.75], [2.0, 1.25])


def draws_from_p0(env) -> None:
    """``TaskTransform(env.p0)`` in front of ``env`` draws tasks inside ``env.task_space`` that
    the env takes and reports."""
    drawn = TransformedEnv(env, TaskTransform(env.p0)).rollout(2)[TASK_KEY]
    assert drawn.shape[-1] == env.task_space.dim
    assert env.task_space.contains(drawn.reshape(-1, env.task_space.dim)).all()


BASE = {
    "point_nav": (PointNavigationEnv, ("goal_x", "goal_y")),
    "pendulum": (PendulumEnv, ("m", "l")),
    "pendulum_mlg": (partial(PendulumEnv, identifiers=("m", "l", "g")), ("m", "l", "g")),
    "acrobot": (AcrobotEnv, ("m1", "m2")),
    "ant_goal": (AntGoalEnv, ("goal_x", "goal_y")),
    "ant_dir": (AntDirEnv, ("direction_angle",)),
    "half_cheetah_vel": (HalfCheetahVelEnv, ("goal_velocity",)),
    "half_cheetah_dir": (HalfCheetahDirEnv, ("direction",)),
    "walker2d_vel": (Walker2dVelEnv, ("goal_velocity",)),
}


@pytest.mark.parametrize("name", list(BASE))
def test_every_env_tells_its_box_and_p0_bare_and_behind_a_user_s_transforms(name):
    make, names = BASE[name]
    env = make(batch_size=(2, 1))
    assert env.task_space.names == names and isinstance(env.p0, BoxUniform)
    wrapped = TransformedEnv(env, Compose(StepCounter(5)))
    assert task_space(wrapped) == wrapped.task_space == env.task_space
    draws_from_p0(env)


@pytest.mark.parametrize("family", [HalfCheetahVelEnv, Walker2dVelEnv])
def test_a_mass_vel_family_tells_velocity_and_mass(family):
    env = physics_task_env(family, MASS, batch_size=(2, 1), seed=0)
    assert env.task_space == VELOCITY and env.p0.space == VELOCITY
    # the layout of TorchRL's examples: a user's TransformedEnv around the package's env
    assert TransformedEnv(env, StepCounter(200)).task_space == VELOCITY
    draws_from_p0(env)


def test_a_physics_transform_a_user_adds_extends_the_box_task_space_reads():
    from armeta_rl.envs.mujoco_tasks import PhysicsTaskTransform

    env = TransformedEnv(HalfCheetahVelEnv(batch_size=(2, 1)),
                         Compose(StepCounter(200), PhysicsTaskTransform(MASS)))
    assert task_space(env) == VELOCITY


@pytest.mark.parametrize("num_tasks", [None, 2])
def test_a_gymnasium_family_tells_its_box(num_tasks):
    family = load_task_family(POLE)
    env = make_gym_task_env(family, num_tasks=num_tasks, max_steps=20)
    assert env.task_space == family.space
    draws_from_p0(env)


def test_batched_envs_tell_one_box_before_and_after_they_start():
    env = TaskSerialEnv(2, partial(PendulumEnv, batch_size=(3,)))
    assert env.task_space == PendulumEnv().task_space  # before the first reset
    env.reset()
    assert env.task_space == PendulumEnv().task_space and env.p0.space == env.task_space
    assert TransformedEnv(env, StepCounter(20)).task_space == env.task_space
    env.close()


def test_batched_workers_of_different_boxes_are_refused_in_one_line():
    env = TaskSerialEnv(2, [partial(PendulumEnv, batch_size=(3,)),
                            partial(PendulumEnv, batch_size=(3,), identifiers=("m", "g"))])
    with pytest.raises(ConfigError, match="workers differ in their task space") as error:
        env.task_space  # noqa: B018
    assert "\n" not in str(error.value)


def test_a_parallel_env_tells_its_box_and_torchrl_s_own_is_refused_in_one_line():
    make = partial(physics_task_env, HalfCheetahVelEnv, MASS, batch_size=(2, 1))
    env = TaskParallelEnv(2, make, mp_start_method="fork")
    assert env.task_space == VELOCITY  # read without starting the workers
    assert env.is_closed
    with pytest.raises(ConfigError, match="TaskParallelEnv") as error:
        task_space(ParallelEnv(2, make, mp_start_method="fork"))
    assert "\n" not in str(error.value)


def warp_overrides(benchmark: str) -> tuple[str, ...]:
    """A MuJoCo Warp benchmark on warp's CPU device."""
    if not benchmark.endswith("_warp"):
        return ()
    nested = "mass_vel" in benchmark  # the warp env under the mass-scale transform
    return (f"benchmark.collector.make_env.{'make_env.' if nested else ''}warp_device=cpu",)


def episode_benchmarks() -> list:
    cases = []
    for name in BENCHMARKS:
        cfg = compose_train(f"benchmark={name}")
        target = cfg.benchmark.collector["_target_"]
        if "Sinusoid" in target or "SysId" in target or "Ray" in target:
            continue  # no env; a Ray benchmark's env is its plain benchmark's (ant_goal)
        marks = ([pytest.mark.skipif(not _has_warp(), reason="MuJoCo Warp is not installed")]
                 if name.endswith("_warp") else [])
        cases.append(pytest.param(name, marks=marks))
    return cases


def _has_warp() -> bool:
    try:
        import mujoco_warp  # noqa: F401
        import warp  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.mark.parametrize("benchmark", episode_benchmarks())
def test_every_benchmark_s_env_tells_the_box_it_trains_on(benchmark):
    cfg = compose_train(f"benchmark={benchmark}", *warp_overrides(benchmark))
    collector = collector_of(cfg)
    assert isinstance(collector, EpisodeCollector)
    env = collector.probe_env()
    try:
        assert env.task_space == task_space(env) == build_space(validate(cfg).benchmark.space)
        draws_from_p0(env)
    finally:
        env.close()


def test_the_sys_id_benchmarks_envs_tell_their_box():
    for benchmark in ("pendulum_uniform", "pendulum_gravity", "acrobot_uniform"):
        config = validate(compose_train(f"benchmark={benchmark}")).benchmark
        make = PendulumEnv if benchmark.startswith("pendulum") else AcrobotEnv
        names = config.collector.get("identifiers") or make.param_names
        env = make(batch_size=(1,), identifiers=names)
        box = build_space(config.space)
        assert env.task_space.names == box.names
        assert bool(env.task_space.contains(torch.tensor([box.low, box.high])).all())
