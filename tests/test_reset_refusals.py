"""A misplaced identifier key is refused where TorchRL users put their transforms: bare, behind
a TransformedEnv, and in front of and inside the package's batched envs
(``TransformedEnv(TaskSerialEnv(...))``, ``TransformedEnv(TaskParallelEnv(...))``); a refused
reset of a ``TaskParallelEnv`` reaches the caller as the one-line IdentifierError with its
workers alive; identifiers nested by name (TorchRL's pendulum tutorial) are taken; and a reset
is refused by the same rule in every layout."""

from __future__ import annotations

from functools import partial

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, RewardSum, StepCounter, TransformedEnv

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
    TaskTransformedEnv,
    Walker2dVelEnv,
)
from armeta_rl.envs.mujoco_tasks import physics_task_env
from armeta_rl.errors import IdentifierError
from armeta_rl.tasks import TASK_KEY

MASS = [{"name": "mass_scale", "kind": "body_mass_only_scale", "target": "all", "low": 0.75,
         "high": 1.25}]
ENVS = {
    "point_nav": PointNavigationEnv,
    "pendulum": PendulumEnv,
    "acrobot": AcrobotEnv,
    "ant_goal": partial(AntGoalEnv, threads=1),
    "ant_dir": AntDirEnv,
    "half_cheetah_vel": HalfCheetahVelEnv,
    "half_cheetah_dir": HalfCheetahDirEnv,
    "walker2d_vel": Walker2dVelEnv,
    "half_cheetah_mass_vel": partial(physics_task_env, HalfCheetahVelEnv, MASS),
}
WORKER = (3,)  # each worker's batch
LAYOUTS = {
    "bare": lambda make: make(batch_size=(2, 3)),
    "transformed": lambda make: TransformedEnv(make(batch_size=(2, 3)), StepCounter(20)),
    "serial": lambda make: TransformedEnv(TaskSerialEnv(2, partial(make, batch_size=WORKER)),
                                          Compose(StepCounter(20), RewardSum())),
}


def refusal(env, entries: dict) -> str:
    """The one line ``env.reset`` refuses ``entries`` with."""
    with pytest.raises(IdentifierError) as error:
        env.reset(TensorDict(entries, env.batch_size))
    message = str(error.value)
    assert "\n" not in message and isinstance(error.value, ValueError)
    return message


def params_of(env, values: list[float]) -> torch.Tensor:
    return torch.tensor(values).expand(*env.batch_size, len(values))


PARALLEL = lambda make: TransformedEnv(TaskParallelEnv(  # noqa: E731
    2, partial(make, batch_size=WORKER), mp_start_method="fork"), StepCounter(20))
MISSPELLED = [(name, layout) for name in ENVS for layout in LAYOUTS] + [
    (name, "parallel") for name in ("point_nav", "pendulum", "half_cheetah_mass_vel")]


@pytest.mark.parametrize(("name", "layout"), MISSPELLED)
def test_a_misspelled_key_is_refused_in_every_layout(name, layout):
    env = {**LAYOUTS, "parallel": PARALLEL}[layout](ENVS[name])
    try:
        width = env.task_space.dim
        message = refusal(env, {"param": torch.full((*env.batch_size, width), 0.9)})
        if layout == "bare":
            assert message.startswith("tensordict key 'param' = ")
        else:  # a TransformedEnv dropped it: the reset reached the env without identifiers
            assert message.startswith("tensordict key 'params' = missing: a full reset")
        # the same reset with the key spelled right is taken
        given = env.reset(TensorDict({TASK_KEY: env.p0.sample_params(1)[0].float().expand(
            *env.batch_size, width)}, env.batch_size))
        assert given[TASK_KEY].shape == (*env.batch_size, width)
    finally:
        env.close()


def test_the_package_s_transformed_env_refuses_a_misspelled_key_in_a_partial_reset():
    """TorchRL's TransformedEnv drops keys outside its state spec before anything below sees
    them; TaskTransformedEnv refuses them first, with or without ``"_reset"``."""
    env = TaskTransformedEnv(TaskSerialEnv(2, partial(PendulumEnv, batch_size=WORKER)),
                             StepCounter(20))
    env.reset()
    partial_reset = torch.zeros(2, 3, 1, dtype=torch.bool)
    partial_reset[0] = True
    message = refusal(env, {"param": torch.ones(2, 3, 2), "_reset": partial_reset})
    assert message.startswith("tensordict key 'param' = ")
    env.close()


@pytest.mark.parametrize("name", ["pendulum", "half_cheetah_mass_vel"])
def test_a_parallel_env_refuses_in_the_caller_with_its_workers_alive(name):
    make = partial(ENVS[name], batch_size=WORKER)
    env = TransformedEnv(TaskParallelEnv(2, make, mp_start_method="fork", num_threads=1,
                                         num_sub_threads=1), StepCounter(20))
    width = env.task_space.dim
    try:
        env.reset()
        workers = env.base_env._workers
        outside = [v - 10.0 for v in env.task_space.low]  # beyond every env's interval
        for entries in ({"param": torch.ones(2, 3, width)},
                        {TASK_KEY: torch.tensor(outside).expand(2, 3, width)},
                        {TASK_KEY: torch.ones(2, 3, width + 1)}):
            refusal(env, entries)
            assert all(worker.is_alive() for worker in workers)
        good = torch.tensor(env.task_space.low).expand(2, 3, width)
        data = env.rollout(3, tensordict=env.reset(TensorDict({TASK_KEY: good}, [2, 3])),
                           auto_reset=False)
        assert torch.equal(data[TASK_KEY], good[:, :, None].expand(2, 3, 3, width).float())
    finally:
        env.close()  # raises if a worker died
    assert not any(worker.is_alive() for worker in workers)


NESTED = {"m": 0.5, "l": 1.5}
NESTED_LAYOUTS = {
    **LAYOUTS,
    "package_transformed": lambda make: TaskTransformedEnv(make(batch_size=(2, 3)),
                                                           StepCounter(20)),
    "parallel": PARALLEL,
}


def nested(batch, values: dict[str, float]) -> TensorDict:
    """Identifiers nested by name, as TorchRL's pendulum tutorial keeps its parameters."""
    return TensorDict({TASK_KEY: TensorDict({k: torch.full(batch, v) for k, v in values.items()},
                                            batch)}, batch)


@pytest.mark.parametrize("layout", list(NESTED_LAYOUTS))
def test_identifiers_nested_by_name_are_taken_or_refused_in_one_line(layout):
    env = NESTED_LAYOUTS[layout](PendulumEnv)
    try:
        out = env.reset(nested(env.batch_size, NESTED))  # any order: taken as (m, l)
        assert torch.equal(out[TASK_KEY], torch.tensor([0.5, 1.5]).expand(2, 3, 2))
        steps = env.rollout(2, tensordict=out, auto_reset=False)
        assert torch.equal(steps[TASK_KEY][:, :, -1], out[TASK_KEY])
        for values in ({"m": 0.5}, {"m": 0.5, "length": 1.5}):
            message = refusal(env, {TASK_KEY: nested(env.batch_size, values)[TASK_KEY]})
            assert "identifiers by name need exactly (m, l)" in message
    finally:
        env.close()


def test_nested_identifiers_name_the_physics_too():
    env = physics_task_env(HalfCheetahVelEnv, MASS, batch_size=(2, 1))
    out = env.reset(nested(env.batch_size, {"mass_scale": 1.2, "goal_velocity": 0.5}))
    assert torch.equal(out[TASK_KEY], torch.tensor([0.5, 1.2]).expand(2, 1, 2))


@pytest.mark.parametrize("layout", ["bare", "transformed", "serial"])
def test_an_unrelated_key_is_refused_alike_bare_and_behind_transforms(layout):
    """A full reset whose TensorDict carries nothing the env reads is refused in every layout
    (behind a transform, that is all that is left of a misspelled key); a partial reset keeps
    its entries' tasks, and ``env.reset()`` without a TensorDict the stored ones."""
    env = LAYOUTS[layout](PendulumEnv)
    try:
        message = refusal(env, {"mass": torch.ones(2, 3, 1)})
        assert message.startswith("tensordict key 'params' = missing: a full reset")
        start = env.reset(TensorDict({TASK_KEY: params_of(env, [0.5, 1.5])}, [2, 3]))
        assert torch.equal(env.reset()[TASK_KEY], start[TASK_KEY])
        partial_reset = TensorDict({"_reset": torch.ones(2, 3, 1, dtype=torch.bool),
                                    "mass": torch.ones(2, 3, 1)}, [2, 3])
        assert torch.equal(env.reset(partial_reset)[TASK_KEY], start[TASK_KEY])
    finally:
        env.close()


def test_a_start_state_without_identifiers_is_still_a_reset_the_env_reads():
    env = PendulumEnv(batch_size=(2,))
    state = torch.tensor([[0.5, 0.0], [1.0, 0.0]])
    out = env.reset(TensorDict({"state": state}, [2]), from_state=True)
    assert torch.equal(out["state"], state)
