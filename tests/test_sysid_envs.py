"""System-identification environments and collector.

The batched torch dynamics are checked against gymnasium's own Pendulum-v1 / Acrobot-v1 with the
same identifiers, state and actions; the identifiers must survive TorchRL's automatic resets.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.collectors.sysid import SysIdCollector
from armeta_rl.envs.acrobot import AcrobotEnv
from armeta_rl.envs.pendulum import PendulumEnv
from armeta_rl.errors import ConfigError

PENDULUM_PARAMS = [(1.0, 1.0), (0.4, 1.6), (1.6, 0.4), (0.7, 1.25)]
ACROBOT_PARAMS = [(1.0, 1.0), (0.4, 1.6), (1.6, 0.4), (1.3, 0.9)]
STEPS = 100


def _reset_to(env, params: torch.Tensor, state: torch.Tensor) -> TensorDict:
    """Reset a ``[n, 1]`` env to given identifiers ``[n, d]`` and states ``[n, s]``."""
    td = TensorDict({"params": params[:, None], "state": state[:, None]}, env.batch_size)
    return env.reset(td, from_state=True)


def gymnasium_envs(env_id: str, attributes: tuple[str, ...], params: list, rng) -> list:
    """One unwrapped gymnasium env per identifier tuple, its physical ``attributes`` set to the
    tuple and reset with a seed from ``rng``."""
    envs = []
    for values in params:
        env = gym.make(env_id).unwrapped
        for attribute, value in zip(attributes, values, strict=True):
            setattr(env, attribute, value)
        env.reset(seed=int(rng.integers(1 << 30)))
        envs.append(env)
    return envs


def test_pendulum_matches_gymnasium():
    rng = np.random.default_rng(0)
    gym_envs = gymnasium_envs("Pendulum-v1", ("m", "l"), PENDULUM_PARAMS, rng)
    env = PendulumEnv(batch_size=(len(gym_envs), 1), seed=0, dtype=torch.float64)
    params = torch.tensor(PENDULUM_PARAMS, dtype=torch.float64)
    state = torch.tensor(np.stack([g.state for g in gym_envs]))
    td = _reset_to(env, params, state)
    for _ in range(STEPS):
        # Torques beyond ±2 exercise the clipping.
        actions = rng.uniform(-2.5, 2.5, size=(len(gym_envs), 1))
        gym_out = [g.step(a.astype(np.float32)) for g, a in zip(gym_envs, actions, strict=True)]
        td["action"] = torch.tensor(actions, dtype=torch.float32).to(torch.float64)[:, None]
        out = env.step(td)["next"]
        expected_obs = torch.tensor(np.stack([o[0] for o in gym_out]), dtype=torch.float64)
        expected_reward = torch.tensor([o[1] for o in gym_out], dtype=torch.float64)
        torch.testing.assert_close(out["observation"][:, 0], expected_obs, atol=1e-4, rtol=0)
        torch.testing.assert_close(out["reward"][:, 0, 0], expected_reward, atol=1e-4, rtol=0)
        assert not out["done"].any()
        td = out.clone()


def test_acrobot_matches_gymnasium():
    rng = np.random.default_rng(1)
    gym_envs = gymnasium_envs("Acrobot-v1", ("LINK_MASS_1", "LINK_MASS_2"), ACROBOT_PARAMS, rng)
    for gym_env in gym_envs:
        # A wider start than gymnasium's ±0.1 so the comparison covers large swings.
        gym_env.state = rng.uniform(-1.0, 1.0, size=4)
    # The first acrobot starts above the bar, so it terminates at once and is reset; the last
    # starts at its velocity limits, so its velocities get clipped.
    gym_envs[0].state = np.array([2.5, 0.0, 0.0, 0.0])
    gym_envs[-1].state = np.array([0.0, 0.0, 12.5, 28.2])
    max_velocity = torch.tensor([AcrobotEnv.max_vel_1, AcrobotEnv.max_vel_2], dtype=torch.float64)
    env = AcrobotEnv(batch_size=(len(gym_envs), 1), seed=0, dtype=torch.float64)
    params = torch.tensor(ACROBOT_PARAMS, dtype=torch.float64)
    td = _reset_to(env, params, torch.tensor(np.stack([g.state for g in gym_envs])))
    terminations = clipped = 0
    for _ in range(STEPS):
        actions = rng.integers(0, 3, size=len(gym_envs))
        gym_out = [g.step(int(a)) for g, a in zip(gym_envs, actions, strict=True)]
        td["action"] = torch.tensor(actions)[:, None]
        out = env.step(td)["next"]
        expected_obs = torch.tensor(np.stack([o[0] for o in gym_out]), dtype=torch.float64)
        torch.testing.assert_close(out["observation"][:, 0], expected_obs, atol=1e-4, rtol=0)
        assert out["reward"][:, 0, 0].tolist() == [o[1] for o in gym_out]
        terminated = torch.tensor([o[2] for o in gym_out])
        assert torch.equal(out["terminated"][:, 0, 0], terminated)
        clipped += int((out["state"][:, 0, 2:].abs() == max_velocity).sum())
        td = out.clone()
        if terminated.any():
            # Gymnasium needs a reset after termination: restart both from gymnasium's new state
            # with a partial reset of the finished episodes only.
            terminations += int(terminated.sum())
            for i in terminated.nonzero().flatten().tolist():
                gym_envs[i].reset(seed=int(rng.integers(1 << 30)))
                td["state"][i, 0] = torch.tensor(gym_envs[i].state, dtype=torch.float64)
            td["_reset"] = terminated[:, None, None]
            td = env.reset(td, from_state=True)
    assert terminations >= 1
    assert clipped >= 1


@pytest.mark.parametrize("env_cls", [PendulumEnv, AcrobotEnv])
def test_check_env_specs(env_cls):
    check_env_specs(env_cls(batch_size=(3, 2), seed=0))


def _upright_acrobot(params: torch.Tensor, upright: torch.Tensor) -> tuple[AcrobotEnv, TensorDict]:
    """An acrobot ``[K, E]`` whose ``upright`` episodes terminate at their first step."""
    env = AcrobotEnv(batch_size=upright.shape, seed=0)
    state = torch.zeros(*upright.shape, 4)
    state[..., 0] = torch.where(upright, torch.pi, 0.0)
    td = TensorDict({"params": params, "state": state}, upright.shape)
    return env, env.reset(td, from_state=True)


def test_identifiers_survive_partial_resets_in_rollout():
    params = torch.tensor([[0.5, 1.5], [1.2, 0.7], [0.9, 1.1]])[:, None].expand(3, 2, 2)
    upright = torch.tensor([[True, False], [False, True], [True, True]])
    env, td = _upright_acrobot(params, upright)
    rollout = env.rollout(4, tensordict=td, auto_reset=False, break_when_any_done=False)
    # The upright episodes terminated at the first step and were reset to a rest state.
    assert torch.equal(rollout["next", "terminated"][:, :, 0, 0], upright)
    assert rollout["state"][:, :, 1][upright].abs().max() <= 0.1 + 1e-6
    # The others kept running from their own (hanging) start.
    assert torch.equal(rollout["state"][:, :, 0][~upright], torch.zeros(int((~upright).sum()), 4))
    assert not rollout["next", "done"][~upright].any()
    for key in ("params", ("next", "params")):
        torch.testing.assert_close(rollout[key], params[:, :, None].expand(3, 2, 4, 2))
    # Every transition, before and after the resets, is the physics of its own episode's masses.
    fresh = AcrobotEnv(batch_size=(3, 2), seed=1)
    for t in range(4):
        start = TensorDict({"params": params, "state": rollout["state"][:, :, t]}, (3, 2))
        start = fresh.reset(start, from_state=True).set("action", rollout["action"][:, :, t])
        torch.testing.assert_close(fresh.step(start)["next", "state"],
                                   rollout["next", "state"][:, :, t])


def _policy(env_cls: type) -> TensorDictModule:
    """A deterministic policy of the observation with the action spec's shape: a torque in
    [-2, 2] for the pendulum, an action index in {0, 1, 2} for the acrobot."""
    weights = torch.randn(env_cls.observation_dim, generator=torch.Generator().manual_seed(3))
    if env_cls is PendulumEnv:
        def act(observation):
            return 2 * (observation @ weights).tanh().unsqueeze(-1)
    else:
        def act(observation):
            return ((observation @ weights).sign() + 1).long()
    return TensorDictModule(act, ["observation"], ["action"])


def _both_rollouts(env_cls: type, params: torch.Tensor, steps: int, policy=None,
                   state: torch.Tensor | None = None) -> tuple[list, list]:
    """``env.rollout`` and ``env.transitions`` from the same seeds and reset, each with the env's
    state after it and the next draw of torch's global RNG (the streams they leave behind)."""
    results = []
    for fast in (False, True):
        torch.manual_seed(11)
        env = env_cls(batch_size=params.shape[:-1], seed=5)
        start = TensorDict({"params": params}, params.shape[:-1])
        if state is not None:
            start["state"] = state
        start = env.reset(start, from_state=state is not None)
        if fast:
            rollout = env.transitions(steps, policy)
        else:
            rollout = env.rollout(steps, policy, tensordict=start, auto_reset=False,
                                  break_when_any_done=False)
        results.append([rollout, env._state, torch.rand(2)])
    return results


@pytest.mark.parametrize("env_cls", [PendulumEnv, AcrobotEnv])
@pytest.mark.parametrize("batch", [(16, 1), (4, 5), (3,), (2, 3, 2)])
@pytest.mark.parametrize("acting", ["random", "policy"])
def test_transitions_equal_env_rollout_bit_for_bit(env_cls, batch, acting):
    """The fast rollout of the system-identification collector is ``env.rollout`` on the public
    env: every key it writes, at every step, and the env state and RNG stream it leaves."""
    params = 0.4 + 1.2 * torch.rand(*batch, 2, generator=torch.Generator().manual_seed(0))
    policy = None if acting == "random" else _policy(env_cls)
    (slow, slow_state, slow_draw), (fast, fast_state, fast_draw) = _both_rollouts(
        env_cls, params, 40, policy)
    assert fast.batch_size == slow.batch_size
    for key in fast.keys(True, True):
        assert torch.equal(fast[key], slow[key]), key
    assert torch.equal(fast_state, slow_state) and torch.equal(fast_draw, slow_draw)


@pytest.mark.parametrize("acting", ["random", "policy"])
def test_transitions_equal_env_rollout_through_partial_resets(acting):
    """Acrobot episodes that terminate are reset between steps as TorchRL's automatic partial
    reset does: the same new initial states, the same transitions after them."""
    params = torch.tensor([[0.5, 1.5], [1.2, 0.7], [0.9, 1.1]])[:, None].expand(3, 2, 2)
    upright = torch.tensor([[True, False], [False, True], [True, True]])
    state = torch.zeros(3, 2, 4)
    state[..., 0] = torch.where(upright, torch.pi, 0.0)
    policy = None if acting == "random" else _policy(AcrobotEnv)
    (slow, slow_state, slow_draw), (fast, fast_state, fast_draw) = _both_rollouts(
        AcrobotEnv, params, 6, policy, state)
    assert torch.equal(slow["next", "terminated"][:, :, 0, 0], upright)  # resets happened
    for key in fast.keys(True, True):
        assert torch.equal(fast[key], slow[key]), key
    assert torch.equal(fast_state, slow_state) and torch.equal(fast_draw, slow_draw)


@pytest.mark.parametrize("env_cls", [PendulumEnv, AcrobotEnv])
def test_identifiers_survive_resets_in_torchrl_collector(env_cls):
    env = env_cls(batch_size=(4, 2), seed=0)
    params = 0.4 + 1.2 * torch.rand(4, 1, 2).expand(4, 2, 2)
    env.reset(TensorDict({"params": params}, env.batch_size))
    # Trajectories of 3 frames: the collector truncates and partially resets every third step.
    collector = Collector(env, None, frames_per_batch=8 * 6, total_frames=8 * 12,
                          max_frames_per_traj=3)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch["next", "truncated"].any()
        torch.testing.assert_close(batch["params"], params[:, :, None].expand_as(batch["params"]))


@pytest.mark.parametrize("env_cls", [PendulumEnv, AcrobotEnv])
def test_seeded_env_is_reproducible(env_cls):
    def run(seed: int) -> TensorDict:
        torch.manual_seed(seed)
        env = env_cls(batch_size=(2, 3), seed=seed)
        return env.rollout(20, break_when_any_done=False)

    first, second, other = run(0), run(0), run(1)
    torch.testing.assert_close(first["next", "observation"], second["next", "observation"])
    assert not torch.allclose(first["next", "observation"], other["next", "observation"])


def _tasks(n: int) -> TensorDict:
    return TensorDict({"params": 0.4 + 1.2 * torch.rand(n, 2)}, batch_size=[n])


def _sort_rows(rows: torch.Tensor) -> torch.Tensor:
    """Rows in lexicographic order (stable sorts from the last column to the first)."""
    for column in reversed(range(rows.shape[1])):
        rows = rows[rows[:, column].argsort(stable=True)]
    return rows


@pytest.mark.parametrize("make_env", [PendulumEnv, AcrobotEnv])
def test_collector_shapes_and_split(make_env):
    collector = SysIdCollector(make_env, n_transitions=200, n_support=10)
    assert isinstance(collector, TaskCollector)
    torch.manual_seed(0)
    tasks = _tasks(5)
    data = collector.collect(tasks)
    size = collector.in_features, collector.out_features
    assert data.batch_size == torch.Size([5])
    assert data["support", "x"].shape == (5, 10, size[0])
    assert data["support", "y"].shape == (5, 10, size[1])
    assert data["query", "x"].shape == (5, 190, size[0])
    assert data["query", "y"].shape == (5, 190, size[1])
    # Support and query together are exactly the rollout's transitions, in a per-task order.
    torch.manual_seed(0)
    _tasks(5)
    rollout = collector.rollout(tasks["params"]).reshape(5, 200)
    expected = torch.cat([rollout["observation"], collector.env_cls.torque(rollout["action"])], -1)
    got = torch.cat([data["support", "x"], data["query", "x"]], 1)
    for task_expected, task_got in zip(expected, got, strict=True):
        torch.testing.assert_close(_sort_rows(task_got), _sort_rows(task_expected))
    assert not torch.equal(got[0], expected[0]), "the split should be random, not the time order"


def test_collector_pairs_pendulum_inputs_with_their_physics():
    """Each target is the next state of its own input under the task's (m, l)."""
    torch.manual_seed(1)
    tasks = _tasks(4)
    data = SysIdCollector(PendulumEnv, target="delta", normalize="none").collect(tasks)
    x, y = data["query", "x"].double(), data["query", "y"].double()
    mass, length = tasks["params"].double().unbind(-1)
    cos, sin, speed, torque = x.unbind(-1)
    acceleration = 15 / length[:, None] * sin + 3 / (mass * length**2)[:, None] * torque
    next_speed = (speed + acceleration * 0.05).clamp(-8, 8)
    torch.testing.assert_close(y[..., 2], next_speed - speed, atol=1e-4, rtol=0)
    angle = torch.atan2(sin, cos) + next_speed * 0.05
    torch.testing.assert_close(y[..., 0], angle.cos() - cos, atol=1e-4, rtol=0)


@pytest.mark.parametrize("make_env", [PendulumEnv, AcrobotEnv])
def test_collector_targets_and_scaling(make_env):
    kwargs = {"episodes": 4, "n_transitions": 40, "n_support": 5}
    torch.manual_seed(2)
    tasks = _tasks(3)
    delta = SysIdCollector(make_env, target="delta", **kwargs).collect(tasks)
    torch.manual_seed(2)
    _tasks(3)
    absolute = SysIdCollector(make_env, target="next", normalize="scale", **kwargs).collect(tasks)
    collector = SysIdCollector(make_env, target="next", normalize="scale", **kwargs)
    observation = delta["query", "x"][..., : collector.out_features]
    torch.testing.assert_close(absolute["query", "x"] * collector.x_scale, delta["query", "x"])
    torch.testing.assert_close(absolute["query", "y"] * collector.y_scale,
                               observation + delta["query", "y"])
    assert absolute["query", "x"].abs().max() <= 1.0


@pytest.mark.parametrize("make_env", [PendulumEnv, AcrobotEnv])
def test_seeded_collection_is_reproducible(make_env):
    collector = SysIdCollector(make_env)
    torch.manual_seed(3)
    first = collector.collect(_tasks(4))
    torch.manual_seed(3)
    second = SysIdCollector(make_env).collect(_tasks(4))
    third = collector.collect(_tasks(4))
    assert (first == second).all()
    assert not torch.equal(first["query", "y"], third["query", "y"])


@pytest.mark.parametrize(("target", "normalize"), [("delta", "none"), ("next", "none"),
                                                   ("next", "scale")])
def test_collected_data_can_be_differentiated_through(target, normalize):
    """The rollout runs in inference mode, but the data ``collect`` returns are ordinary tensors:
    a network's backward pass saves them (inference tensors would raise there)."""
    collector = SysIdCollector(AcrobotEnv, episodes=1, target=target, normalize=normalize)
    torch.manual_seed(0)
    data = collector.collect(_tasks(3))
    assert collector.rollout(_tasks(3)["params"])["observation"].is_inference()
    network = torch.nn.Linear(collector.in_features, collector.out_features)
    for part in ("support", "query"):
        x, y = data[part, "x"], data[part, "y"]
        assert not x.is_inference() and not y.is_inference()
        network.zero_grad()
        (network(x) - y).square().mean().backward()
        assert torch.isfinite(network.weight.grad).all() and network.weight.grad.abs().sum() > 0


@pytest.mark.parametrize(
    ("key", "kwargs"),
    [
        ("make_env", {"make_env": lambda **kwargs: TransformedEnv(PendulumEnv(**kwargs))}),
        ("n_support", {"n_support": 200}),
        ("episodes", {"episodes": 7}),
        ("target", {"target": "state"}),
        ("normalize", {"normalize": "zscore"}),
        ("compile", {"compile": "fast"}),
    ],
)
def test_collector_rejects_bad_options(key, kwargs):
    with pytest.raises(ConfigError) as error:
        SysIdCollector(**kwargs)
    assert error.value.key == f"benchmark.collector.{key}"


class LongPendulumEnv(PendulumEnv):
    """A family of its own, in this module alone: the pendulum, its default length doubled."""

    identifier_defaults = {**PendulumEnv.identifier_defaults, "l": 2.0}


def test_a_new_family_is_its_env_alone():
    """The collector takes any factory of an identified env: a family needs no registry entry,
    and the transitions are its env's (seeded alike, the doubled default length moves the
    pendulum otherwise)."""
    tasks = TensorDict({"params": torch.tensor([[1.0, 9.8]])}, [1])
    collected = {}
    for family in (PendulumEnv, LongPendulumEnv):
        torch.manual_seed(0)
        collector = SysIdCollector(family, n_transitions=20, n_support=5, episodes=2,
                                   identifiers=["m", "g"])
        collected[family] = collector.collect(tasks)
    assert collected[LongPendulumEnv]["support", "x"].shape == (1, 5, collector.in_features)
    assert not torch.equal(collected[PendulumEnv]["query", "y"],
                           collected[LongPendulumEnv]["query", "y"])
