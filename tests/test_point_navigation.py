"""PointNavigationEnv: specs, dynamics, goals across automatic resets, sparse regions, TorchRL
rollouts/collectors/transforms, seeding; and the episode collector's masking."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.envs import RewardSum, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from armeta_rl.collectors.episodes import PointNavigationCollector, episode_returns, valid_mask
from armeta_rl.envs.point_navigation import (
    PAPER_SPARSE_REGIONS,
    PointNavigationEnv,
    blind_return,
    fixed_path_return,
    reference_return,
)
from armeta_rl.errors import ConfigError
from armeta_rl.rl.policy import GaussianMLP, make_actor


def reset_with_goals(env: PointNavigationEnv, goals: torch.Tensor) -> TensorDict:
    return env.reset(TensorDict({"params": goals}, env.batch_size))


def test_check_env_specs_plain_and_sparse() -> None:
    check_env_specs(PointNavigationEnv((3, 4), seed=0))
    check_env_specs(PointNavigationEnv((2, 5), sparse_regions=PAPER_SPARSE_REGIONS, seed=1))


def test_step_clips_action_and_rewards_minus_distance() -> None:
    env = PointNavigationEnv((1, 2), seed=0)
    goals = torch.tensor([[[0.3, -0.2], [0.05, 0.0]]])
    reset_with_goals(env, goals)
    action = torch.tensor([[[1.0, -1.0], [0.05, 0.0]]])
    out = env.step(TensorDict({"action": action}, env.batch_size))["next"]
    expected_position = torch.tensor([[[0.1, -0.1], [0.05, 0.0]]])
    torch.testing.assert_close(out["observation"], expected_position)
    distance = (expected_position - goals).norm(dim=-1, keepdim=True)
    torch.testing.assert_close(out["reward"], -distance)
    # the second robot lands on its goal: terminated, not truncated
    assert out["terminated"].squeeze(-1).tolist() == [[False, True]]
    assert not out["truncated"].any()


def test_squared_distance_option() -> None:
    env = PointNavigationEnv((1, 1), squared_distance=True, seed=0)
    reset_with_goals(env, torch.tensor([[[0.4, 0.3]]]))
    out = env.step(TensorDict({"action": torch.zeros(1, 1, 2)}, env.batch_size))["next"]
    torch.testing.assert_close(out["reward"], torch.tensor([[[-0.25]]]))


def test_time_limit_truncates() -> None:
    env = PointNavigationEnv((2, 3), max_steps=7, seed=0)
    start = reset_with_goals(env, torch.full((2, 3, 2), 0.5))
    rollout = env.rollout(7, auto_reset=False, tensordict=start)
    assert rollout.batch_size == (2, 3, 7)
    truncated = rollout["next", "truncated"].squeeze(-1)
    assert truncated[..., -1].all() and not truncated[..., :-1].any()


def test_goals_survive_automatic_resets() -> None:
    torch.manual_seed(0)  # the random actions: no walk of this seed reaches its goal early
    env = PointNavigationEnv((3, 2), max_steps=10, seed=0)
    goals = torch.tensor([[0.4, -0.3], [-0.2, 0.1], [0.0, 0.45]])[:, None].expand(3, 2, 2)
    start = reset_with_goals(env, goals)
    # 25 steps with a 10-step limit: two automatic (partial) resets inside env.rollout
    rollout = env.rollout(25, tensordict=start, auto_reset=False, break_when_any_done=False)
    done = rollout["next", "done"].squeeze(-1)
    assert done[..., 9].all() and done[..., 19].all()
    # after each reset the robot is back at the origin ...
    assert (rollout["observation"][..., [10, 20], :] == 0).all()
    # ... and every step, before and after the resets, was played against the same goal
    assert (rollout["params"] == goals[:, :, None]).all()
    assert (rollout["next", "params"] == goals[:, :, None]).all()
    offset = rollout["next", "observation"] - goals[:, :, None]
    torch.testing.assert_close(rollout["next", "reward"], -offset.norm(dim=-1, keepdim=True))


def test_goals_survive_reset_and_automatic_resets_under_transformed_env() -> None:
    env = TransformedEnv(PointNavigationEnv((2, 3), max_steps=4, seed=0), StepCounter())
    env.append_transform(RewardSum())
    goals = torch.tensor([[0.4, -0.3], [-0.2, 0.1]])[:, None].expand(2, 3, 2).clone()
    start = env.reset(TensorDict({"params": goals}, env.batch_size))
    assert torch.equal(start["params"], goals)
    rollout = env.rollout(10, tensordict=start, auto_reset=False, break_when_any_done=False)
    assert rollout["next", "done"].squeeze(-1)[..., 3].all()  # reset inside the rollout
    assert (rollout["params"] == goals[:, :, None]).all()
    offset = rollout["next", "observation"] - goals[:, :, None]
    torch.testing.assert_close(rollout["next", "reward"], -offset.norm(dim=-1, keepdim=True))


def test_reset_without_goal_keeps_goals_and_seed_draws_defaults() -> None:
    a, b, c = (PointNavigationEnv((4, 2), seed=s) for s in (3, 3, 4))
    goals_a = a.reset()["params"]
    torch.testing.assert_close(goals_a, b.reset()["params"])
    assert not torch.equal(goals_a, c.reset()["params"])
    assert goals_a.abs().max() <= 0.5
    new = torch.full((4, 2, 2), 0.2)
    reset_with_goals(a, new)
    assert torch.equal(a.reset()["params"], new)


@pytest.mark.parametrize(
    ("goal", "scale"),
    [
        ((-0.4, 0.3), 0.6),
        ((-0.25, 0.25), 0.6),  # region edges are inside
        ((0.3, -0.45), 0.4),
        ((0.3, 0.3), 1.0),
        ((-0.4, -0.3), 1.0),
        ((-0.2, 0.4), 1.0),
    ],
)
def test_sparse_regions_scale_step_rewards(goal: tuple[float, float], scale: float) -> None:
    plain = PointNavigationEnv((1, 1), seed=0)
    sparse = PointNavigationEnv((1, 1), sparse_regions=PAPER_SPARSE_REGIONS, seed=0)
    goals = torch.tensor(goal).view(1, 1, 2)
    actions = torch.tensor([[0.07, -0.02], [-0.1, 0.1], [0.03, 0.05]])
    rewards = []
    for env in (plain, sparse):
        td = reset_with_goals(env, goals)
        per_step = []
        for action in actions:
            td = env.step(td.set("action", action.view(1, 1, 2)))
            per_step.append(td["next", "reward"])
            td = td["next"]
        rewards.append(torch.stack(per_step))
    assert (rewards[0] < 0).all()
    torch.testing.assert_close(rewards[1], scale * rewards[0])


def test_custom_regions_and_bad_regions() -> None:
    env = PointNavigationEnv((1, 1), sparse_regions=[((0.0, 0.5), (0.0, 0.5), 0.1)], seed=0)
    reset_with_goals(env, torch.tensor([[[0.2, 0.2]]]))
    reward = env.step(TensorDict({"action": torch.zeros(1, 1, 2)}, [1, 1]))["next", "reward"]
    torch.testing.assert_close(reward, torch.tensor([[[-0.1 * 0.08**0.5]]]))
    with pytest.raises(ConfigError, match="sparse_regions"):
        PointNavigationEnv((1, 1), sparse_regions=[((0.5, 0.0), (0.0, 0.5), 0.1)])
    with pytest.raises(ConfigError, match="sparse_regions"):
        PointNavigationEnv((1, 1), sparse_regions=[(0.5, 0.1)])
    with pytest.raises(ConfigError, match="max_steps"):
        PointNavigationEnv((1, 1), max_steps=0)


def test_runs_under_collector_with_probabilistic_actor_and_transforms() -> None:
    torch.manual_seed(0)
    env = TransformedEnv(PointNavigationEnv((2, 3), max_steps=5, seed=0), StepCounter())
    env.append_transform(RewardSum())
    check_env_specs(env)
    actor = make_actor(GaussianMLP())
    collector = Collector(
        env, actor, frames_per_batch=2 * 3 * 8, total_frames=2 * 3 * 16,
        auto_register_policy_transforms=False,
    )
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch.batch_size == (2, 3, 8)
        goals = batch["params"]
        assert (goals == goals[:, :, :1]).all()  # constant across the resets at steps 5 and 10
        assert (batch["next", "step_count"] <= 5).all()
        # the actor's samples are stochastic and its log-probs match a diagonal Gaussian
        logp = torch.distributions.Normal(batch["loc"], batch["scale"]).log_prob(batch["action"])
        torch.testing.assert_close(batch["action_log_prob"], logp.sum(-1))
    # the first batch starts with fresh episodes that end at the 5-step limit; RewardSum's
    # episode return there equals the sum of the step rewards
    first = batches[0]
    assert first["next", "done"].squeeze(-1)[..., 4].all()
    in_episode = first["next", "reward"][..., :5, 0].sum(-1)
    torch.testing.assert_close(first["next", "episode_reward"][..., 4, 0], in_episode)


def test_valid_mask_keeps_only_the_first_episode() -> None:
    done = torch.tensor([[False, False, True, False, True], [False] * 4 + [True]])
    expected = torch.tensor([[True, True, True, False, False], [True] * 5])
    assert torch.equal(valid_mask(done), expected)


def test_episode_collector_shapes_goals_and_masked_returns() -> None:
    torch.manual_seed(0)
    collector = PointNavigationCollector(episodes=3, max_steps=20, seed=0)
    net = GaussianMLP()
    goals = torch.tensor([[0.0, 0.005], [0.3, -0.4]])
    data = collector.collect(TensorDict({"params": goals}, [2]), policy=net)
    assert data.batch_size == (2, 3, 20)
    assert (data["params"] == goals[:, None, None]).all()
    # returns count only the steps of the first episode of each batch entry
    manual = torch.zeros(2, 3)
    for k in range(2):
        for e in range(3):
            for t in range(20):
                manual[k, e] += data["reward"][k, e, t, 0]
                if data["done"][k, e, t, 0]:
                    break
    torch.testing.assert_close(episode_returns(data), manual)
    with pytest.raises(ConfigError, match="episodes"):
        PointNavigationCollector(episodes=0)
    with pytest.raises(ConfigError, match="sparse_regions"):
        PointNavigationCollector(sparse_regions=[((0.0, 0.5), (0.0, 0.5), -1.0)])


def test_episode_collector_acts_with_each_tasks_parameters() -> None:
    torch.manual_seed(1)
    net = GaussianMLP()
    params = TensorDict.from_module(net).detach().expand(2).clone()
    # task 0 always pushes +x, task 1 always pushes -y, both (nearly) deterministically
    params["mean", "4", "weight"].zero_()
    params["mean", "4", "bias"].copy_(torch.tensor([[1.0, 0.0], [0.0, -1.0]]))
    params["log_std"].fill_(-12.0)
    collector = PointNavigationCollector(episodes=2, max_steps=4, seed=0)
    goals = TensorDict({"params": torch.tensor([[0.5, 0.5], [0.5, 0.5]])}, [2])
    data = collector.collect(goals, params, policy=net)
    final = data["observation"][:, :, -1] + data["action"][:, :, -1].clamp(-0.1, 0.1)
    torch.testing.assert_close(final[0], torch.tensor([[0.4, 0.0]] * 2), atol=1e-4, rtol=0)
    torch.testing.assert_close(final[1], torch.tensor([[0.0, -0.4]] * 2), atol=1e-4, rtol=0)
    expected_x = torch.tensor([0.1, 0.2, 0.3])
    torch.testing.assert_close(data["observation"][0, 0, 1:, 0], expected_x, atol=1e-4, rtol=0)


TRUNCATED = (((-0.5, -0.25), (0.25, 0.5), 0.2), ((0.25, 0.5), (-0.5, -0.25), 0.2))


@pytest.mark.parametrize("regions", [{}, {"sparse_regions": PAPER_SPARSE_REGIONS},
                                     {"truncated_regions": TRUNCATED},
                                     {"truncated_regions": TRUNCATED, "squared_distance": True}])
def test_reference_return_is_the_full_speed_path_and_no_policy_beats_it(regions) -> None:
    torch.manual_seed(0)
    goals = torch.rand(64, 2) - 0.5
    env = PointNavigationEnv((64, 1), max_steps=30, seed=0, **regions)
    reference = reference_return(goals, 30, regions.get("sparse_regions", ()),
                                 regions.get("truncated_regions", ()),
                                 regions.get("squared_distance", False))

    def episode_return(act) -> torch.Tensor:
        td = reset_with_goals(env, goals[:, None])
        total, running = torch.zeros(64), torch.ones(64, dtype=torch.bool)
        for _ in range(30):
            td = env.step(td.set("action", act(td["observation"])))
            total += td["next", "reward"].view(64) * running
            running &= ~td["next", "done"].view(64)
            td = td["next"]
        return total

    greedy = episode_return(lambda position: (goals[:, None] - position).clamp(-0.1, 0.1))
    torch.testing.assert_close(greedy, reference, rtol=1e-5, atol=1e-6)
    for _ in range(5):  # noisy versions of the greedy path and random walks do worse
        noisy = episode_return(lambda p: (goals[:, None] - p).clamp(-0.1, 0.1)
                               + 0.05 * torch.randn(64, 1, 2))
        walk = episode_return(lambda p: 0.1 * (2 * torch.rand(64, 1, 2) - 1))
        assert (noisy <= reference + 1e-5).all() and (walk <= reference + 1e-5).all()


def test_truncated_regions_feel_the_distance_only_within_the_radius() -> None:
    env = PointNavigationEnv((2, 1), truncated_regions=TRUNCATED, seed=0)
    reset_with_goals(env, torch.tensor([[[-0.3, 0.3]], [[-0.1, 0.1]]]))  # in a region, outside
    td = TensorDict({"action": torch.tensor([[[-0.1, 0.1]], [[0.0, 0.0]]])}, [2, 1])
    rewards = []
    for _ in range(2):
        td = env.step(td)
        rewards.append(td["next", "reward"].view(2))
        td = td["next"].set("action", torch.tensor([[[-0.1, 0.1]], [[0.0, 0.0]]]))
    # region goal: at (−0.1, 0.1) it is 0.2·√2 > 0.2 away (reward −0.2, capped), at (−0.2, 0.2)
    # 0.1·√2 < 0.2 (reward −0.1·√2); the goal outside the regions is felt at any distance
    torch.testing.assert_close(rewards[0], torch.tensor([-0.2, -0.1 * 2**0.5]))
    torch.testing.assert_close(rewards[1], torch.tensor([-0.1 * 2**0.5, -0.1 * 2**0.5]))
    with pytest.raises(ConfigError, match="truncated_regions"):
        PointNavigationEnv((1, 1), truncated_regions=[((0.0, 0.5), (0.0, 0.5), -1.0)])


def test_a_scaled_region_changes_the_return_not_the_adaptation() -> None:
    """MAML-TRPO normalizes each task's advantages, so scaling a task's rewards by 0.4 (the
    paper's region) leaves its inner step, hence the adapted policy and its episodes, unchanged:
    the same trajectories score 0.4 times the return. The scaled region is not harder, it only
    looks easier to a loss that reads returns (docs/meta-rl.md)."""
    from armeta_rl.learners.maml_trpo import MAMLTRPOLeader

    returns = []
    for regions in ((), PAPER_SPARSE_REGIONS):
        collector = PointNavigationCollector(episodes=4, max_steps=20, sparse_regions=regions)
        torch.manual_seed(0)
        leader = MAMLTRPOLeader(collector)
        tasks = TensorDict({"params": torch.tensor([[0.3, -0.4], [0.45, -0.3]])}, [2])
        torch.manual_seed(1)
        with torch.no_grad():
            batch = leader.collect(tasks)
        returns.append((batch, episode_returns(batch.valid)))
    (plain, plain_returns), (scaled, scaled_returns) = returns
    torch.testing.assert_close(scaled.valid["action"], plain.valid["action"], rtol=1e-4,
                               atol=1e-5)
    torch.testing.assert_close(scaled.train_advantages, plain.train_advantages, rtol=1e-3,
                               atol=1e-4)
    torch.testing.assert_close(scaled_returns, 0.4 * plain_returns, rtol=1e-4, atol=1e-5)


def _rollouts(batch: tuple[int, ...], goals: torch.Tensor, policy, steps: int,
              regions: dict | None = None, fast_path=None) -> list:
    """``env.rollout`` and ``env.transitions`` (or ``fast_path(env, steps)``) from the same seeds
    and reset, each with the env's position and step count after it and the next draw of
    torch's global RNG; ``regions``: the env's reward regions (default the paper's scaled
    ones)."""
    fast_path = fast_path or (lambda env, steps: env.transitions(steps, policy))
    results = []
    for fast in (False, True):
        torch.manual_seed(2)
        env = PointNavigationEnv(batch, max_steps=7, seed=4,
                                 **(regions or {"sparse_regions": PAPER_SPARSE_REGIONS}))
        start = env.reset(TensorDict({"params": goals}, batch))
        with set_exploration_type(ExplorationType.RANDOM):
            rollout = fast_path(env, steps) if fast else env.rollout(
                steps, policy, tensordict=start, auto_reset=False, break_when_any_done=False)
        results.append([rollout, env._position, env._steps, torch.rand(2)])
    return results


@pytest.mark.parametrize("batch", [(4, 5), (3,), (2, 3, 2)])
@pytest.mark.parametrize("per_task", [False, True])
@pytest.mark.parametrize("path", ["transitions", "gaussian_transitions"])
def test_transitions_equal_env_rollout_bit_for_bit(batch, per_task, path):
    """The fast rollouts are ``env.rollout`` with the same stochastic actor (shared or per-task
    parameters): ``transitions`` with the actor itself, and the collectors'
    ``gaussian_transitions``, a function of tensors alone (what a CUDA graph replays). Every key
    they write at every step, through the automatic resets of truncated episodes (7-step limit in
    20 steps), the env state and the RNG stream left behind."""
    goals = torch.rand(*batch, 2, generator=torch.Generator().manual_seed(0)) - 0.5
    net = GaussianMLP()
    params = None
    if per_task:
        params = TensorDict.from_module(net).detach().expand(batch[0]).clone()
        params.apply_(lambda p: p + 0.1 * torch.randn_like(p))
    actor = make_actor(net, params)
    fast_paths = {"transitions": lambda env, steps: env.transitions(steps, actor),
                  "gaussian_transitions": lambda env, steps: env.gaussian_transitions(
                      steps, net, params)}
    slow, fast = _rollouts(batch, goals, actor, 20, fast_path=fast_paths[path])
    assert fast[0]["next", "truncated"].any()
    for key in fast[0].keys(True, True):
        assert torch.equal(fast[0][key], slow[0][key]), key
    for a, b in zip(fast[1:], slow[1:]):
        assert torch.equal(a, b)


def test_transitions_equal_env_rollout_when_goals_are_reached():
    """Episodes that reach their goal terminate and restart from the origin between steps, as
    in ``env.rollout``: a policy that stays at the origin, with goals there, ends every step."""
    batch = (3, 2)
    stay = TensorDictModule(lambda observation: -observation, ["observation"], ["action"])
    slow, fast = _rollouts(batch, torch.zeros(*batch, 2), stay, 5)
    assert fast[0]["next", "terminated"].all()
    for key in fast[0].keys(True, True):
        assert torch.equal(fast[0][key], slow[0][key]), key


def test_transitions_equal_env_rollout_with_truncated_regions():
    """The sparse robot's capped rewards (``point_nav_sparse``) on the fast path too, bit for bit,
    with goals inside and outside the truncated regions."""
    batch = (4, 5)
    goals = torch.rand(*batch, 2, generator=torch.Generator().manual_seed(1)) - 0.5
    goals[:2] = torch.tensor([-0.4, 0.4])  # in the top-left truncated region
    regions = {"truncated_regions": TRUNCATED}
    slow, fast = _rollouts(batch, goals, make_actor(GaussianMLP()), 20, regions)
    capped = fast[0]["next", "reward"][:2] == -0.2
    assert capped.any() and not capped.all()
    for key in fast[0].keys(True, True):
        assert torch.equal(fast[0][key], slow[0][key]), key
    for a, b in zip(fast[1:], slow[1:]):
        assert torch.equal(a, b)


def test_cuda_graphs_are_a_switch_for_cuda_only() -> None:
    """``graphs`` takes true, false or null (one line naming the key otherwise); a CPU env never
    replays graphs, whatever it is asked."""
    with pytest.raises(ConfigError, match=r"benchmark\.collector\.graphs.*true, false or null"):
        PointNavigationCollector(graphs="maybe")
    assert not PointNavigationCollector(episodes=1, graphs=True).env(1).graphs
    assert not PointNavigationEnv((1, 1), graphs=None).graphs


@pytest.mark.parametrize("squared", [False, True])
def test_a_fixed_paths_return_is_its_rollout_in_the_env(squared):
    """Stepping the env toward a fixed point at full speed (each coordinate's action clipped to
    ±0.1), then staying, gives fixed_path_return's return on every goal, the episode's end at a
    goal included; with the point at the goal it is reference_return."""
    goals = torch.tensor([[0.3, -0.2], [0.05, 0.0], [-0.45, 0.4], [0.4, -0.4]])
    points = torch.tensor([[0.05, 0.0], [0.3, -0.2], [0.2, 0.2]])
    max_steps = 12
    for point in points:
        env = PointNavigationEnv((len(goals), 1), max_steps=max_steps,
                                 sparse_regions=PAPER_SPARSE_REGIONS, squared_distance=squared,
                                 seed=0)
        reset_with_goals(env, goals[:, None])
        position = torch.zeros(len(goals), 1, 2)
        total, alive = torch.zeros(len(goals)), torch.ones(len(goals), dtype=torch.bool)
        for _ in range(max_steps):
            action = (point - position).clamp(-0.1, 0.1)
            out = env.step(TensorDict({"action": action}, env.batch_size))["next"]
            total += out["reward"].reshape(-1) * alive
            alive &= ~out["done"].reshape(-1)
            position = out["observation"]
        expected = fixed_path_return(point.double(), goals.double(), max_steps,
                                     PAPER_SPARSE_REGIONS, squared_distance=squared)
        torch.testing.assert_close(total.double(), expected, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(
        fixed_path_return(goals.double(), goals.double(), max_steps, PAPER_SPARSE_REGIONS),
        reference_return(goals.double(), max_steps, PAPER_SPARSE_REGIONS))


def test_the_blind_reference_by_hand_and_against_every_point_of_a_grid():
    """Goals (±0.2, 0) over 2 steps: every point between them is as good on average, −0.4 (at
    the origin: 0.2 at both steps for both goals). On 60 goals of the paper's env no fixed point
    of a 41 × 41 grid over the box does better on average than the blind reference, which is no
    better than the oracle on any goal; repeated goals do not move it."""
    pair = torch.tensor([[0.2, 0.0], [-0.2, 0.0]], dtype=torch.float64)
    assert float(blind_return(pair, 2).mean()) == pytest.approx(-0.4)
    torch.manual_seed(0)
    goals = torch.rand(60, 2, dtype=torch.float64) - 0.5
    blind = blind_return(goals, 100, PAPER_SPARSE_REGIONS)
    axis = torch.linspace(-0.5, 0.5, 41, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    on_grid = fixed_path_return(grid[:, None], goals, 100, PAPER_SPARSE_REGIONS).mean(-1)
    assert float(blind.mean()) >= float(on_grid.max()) - 1e-9
    assert bool((blind <= reference_return(goals, 100, PAPER_SPARSE_REGIONS) + 1e-9).all())
    torch.testing.assert_close(blind_return(goals.repeat(3, 1), 100, PAPER_SPARSE_REGIONS),
                               blind.repeat(3))
