"""MAML-TRPO pieces: returns, GAE and the linear baseline on hand-computed cases; conjugate
gradient and KL Hessian-vector products against dense linear algebra; the batched inner step and
the rollout policy against per-task loops; the TRPO trust region; and a short seeded training
run."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import pytest
import torch
from tensordict import TensorDict
from torch import Tensor
from torch.func import functional_call
from torchrl.envs.utils import ExplorationType, set_exploration_type

from armeta_rl.collectors.episodes import PointNavigationCollector, valid_mask
from armeta_rl.config import TrainerConfig
from armeta_rl.errors import ConfigError
from armeta_rl.learners.maml_trpo import MAMLTRPOLeader, MamlTrpoOptions, last_step_loss
from armeta_rl.rl.baseline import (
    baseline_features,
    baseline_values,
    discounted_returns,
    episode_mean,
    fit_linear_baseline,
    gae_advantages,
)
from armeta_rl.rl.policy import (
    GaussianActor,
    GaussianMLP,
    kl_divergence,
    loc_scale,
    log_prob,
    make_actor,
)
from armeta_rl.rl.trpo import (
    backtracking_line_search,
    conjugate_gradient,
    flatten,
    mean_kl,
    meta_kl_hessian_vector_product,
    surrogate_loss,
    unflatten,
)
from armeta_rl.tasks import BoxUniform, TaskSpace
from conftest import compose_train, players_of

SPACE = TaskSpace(["goal_x", "goal_y"], [-0.5, -0.5], [0.5, 0.5])


def kl_hessian_vector_product(
    kl: Tensor, params: Sequence[Tensor], damping: float = 1e-5
) -> Callable[[Tensor], Tensor]:
    """Reference v ↦ (∇²_θ KL + damping·I) v by plain double backpropagation.

    ``kl`` must be built with a graph from ``params`` (when the KL is taken at the adapted policy
    of MAML, the graph runs *through* the inner gradient step, giving the second-order Hessian).
    The first gradient is computed once; every product is one more backward pass.
    """
    grads = torch.autograd.grad(kl, params, create_graph=True)
    flat_grad = flatten(grads)

    def product(vector: Tensor) -> Tensor:
        second = torch.autograd.grad(flat_grad @ vector, params, retain_graph=True)
        return flatten(second).detach() + damping * vector

    return product


def trajectories(reward: torch.Tensor, done: torch.Tensor, observation: torch.Tensor) -> TensorDict:
    """A hand-made trajectory batch ``[K, E, T]``."""
    done = done.bool()
    return TensorDict(
        {
            "reward": reward.unsqueeze(-1),
            "done": done.unsqueeze(-1),
            "mask": valid_mask(done),
            "observation": observation,
        },
        batch_size=reward.shape,
    )


def test_discounted_returns_hand_case() -> None:
    reward = torch.tensor([[[1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 4.0]]])
    done = torch.tensor([[[0, 1, 0, 0], [0, 0, 0, 1]]])
    data = trajectories(reward, done, torch.zeros(1, 2, 4, 2))
    returns = discounted_returns(data, 0.5).squeeze(-1)
    expected = torch.tensor([[[1 + 0.5 * 2, 2, 0, 0], [1 + 1 + 0.75 + 0.5, 2 + 1.5 + 1, 3 + 2, 4]]])
    torch.testing.assert_close(returns, expected)


def test_baseline_features_hand_case() -> None:
    observation = torch.tensor([[[[0.1, -0.2], [0.3, 0.4], [9.0, 9.0]]]])
    data = trajectories(torch.zeros(1, 1, 3), torch.tensor([[[0, 1, 0]]]), observation)
    features = baseline_features(data)
    t = 0.01
    expected = torch.tensor(
        [
            [0.1, -0.2, 0.01, 0.04, 0.0, 0.0, 0.0, 1.0],
            [0.3, 0.4, 0.09, 0.16, t, t**2, t**3, 1.0],
            [0.0] * 8,  # after the episode's end
        ]
    )
    torch.testing.assert_close(features[0, 0], expected)


def test_ridge_fit_recovers_per_task_linear_targets() -> None:
    torch.manual_seed(0)
    features = torch.randn(3, 4, 10, 8, dtype=torch.float64)
    coefficients = torch.randn(3, 8, dtype=torch.float64)
    targets = torch.einsum("kdtf,kf->kdt", features, coefficients)
    fitted = fit_linear_baseline(features, targets, reg=1e-10)
    torch.testing.assert_close(fitted, coefficients)
    # with a strong ridge the solution is the regularized normal-equation solution of each task
    design = features[1].reshape(-1, 8)
    ridge = torch.linalg.solve(design.T @ design + 5.0 * torch.eye(8, dtype=torch.float64),
                               design.T @ targets[1].reshape(-1))
    torch.testing.assert_close(fit_linear_baseline(features, targets, reg=5.0)[1], ridge)


def test_gae_matches_hand_recursion_and_is_normalized_per_task() -> None:
    torch.manual_seed(1)
    k, e, t, gamma, lmbda = 2, 3, 6, 0.9, 0.8
    reward = torch.randn(k, e, t)
    done = torch.zeros(k, e, t)
    done[..., -1] = 1
    done[0, 1, 2] = 1
    done[1, 2, 0] = 1
    data = trajectories(reward, done, torch.randn(k, e, t, 2))
    mask = data["mask"]
    values = (baseline_values(data, gamma).squeeze(-1) * mask).tolist()
    raw = torch.zeros(k, e, t)
    for a in range(k):
        for b in range(e):
            following = 0.0
            for s in reversed(range(t)):
                if not mask[a, b, s]:
                    continue
                ends = bool(done[a, b, s])
                next_value = 0.0 if ends else values[a][b][s + 1]
                delta = float(reward[a, b, s]) + gamma * next_value - values[a][b][s]
                following = delta + (0.0 if ends else gamma * lmbda * following)
                raw[a, b, s] = following
    expected = torch.zeros_like(raw)
    for a in range(k):  # every episode weighs equally in the statistics, whatever its length
        mean = sum(raw[a, b][mask[a, b]].mean() for b in range(e)) / e
        variance = sum(((raw[a, b][mask[a, b]] - mean) ** 2).mean() for b in range(e)) / e
        expected[a][mask[a]] = (raw[a][mask[a]] - mean) / (variance.sqrt() + 1e-8)
    torch.testing.assert_close(gae_advantages(data, gamma, lmbda), expected, atol=1e-5, rtol=1e-4)


def small_policy_kl(dtype: torch.dtype = torch.float64):
    """A tiny Gaussian policy, its flat parameters and θ ↦ mean KL(π_θ ‖ π_θ0) on fixed states."""
    torch.manual_seed(2)
    net = GaussianMLP(2, 2, (3,)).to(dtype)
    names = [n for n, _ in net.named_parameters()]
    shapes = [p.detach().clone() for p in net.parameters()]
    observation = torch.randn(40, 2, dtype=dtype)
    with torch.no_grad():  # move log-std away from 0 so the Fisher is not trivially scaled
        net.log_std.fill_(-0.3)
        theta0 = flatten(list(net.parameters())).detach()
        old = net(observation)

    def kl(vector: torch.Tensor) -> torch.Tensor:
        params = dict(zip(names, unflatten(vector, shapes)))
        loc, scale = functional_call(net, params, (observation,))
        return kl_divergence(loc, scale, *old).mean()

    return theta0, kl


def test_kl_hessian_vector_product_and_conjugate_gradient_match_dense_algebra() -> None:
    theta0, kl = small_policy_kl()
    hessian = torch.autograd.functional.hessian(kl, theta0)
    n = theta0.numel()
    damping = 1e-2
    theta = theta0.clone().requires_grad_(True)
    hvp = kl_hessian_vector_product(kl(theta), [theta], damping)
    v = torch.randn(n, dtype=theta0.dtype)
    torch.testing.assert_close(hvp(v), hessian @ v + damping * v)
    # at θ = θ_old the KL Hessian is the Fisher: symmetric positive semi-definite
    assert torch.linalg.eigvalsh(hessian).min() > -1e-10
    b = torch.randn(n, dtype=theta0.dtype)
    exact = torch.linalg.solve(hessian + damping * torch.eye(n, dtype=theta0.dtype), b)
    approx, _ = conjugate_gradient(hvp, b, iterations=4 * n, residual_tol=1e-20)
    torch.testing.assert_close(approx, exact, rtol=1e-6, atol=1e-8)
    # the product A x that CG returns from its residual is the true product
    partial, product = conjugate_gradient(hvp, b, iterations=5)
    torch.testing.assert_close(product, hvp(partial), rtol=1e-8, atol=1e-10)
    # every CG iteration lowers the quadratic model ½xᵀAx − bᵀx that it minimizes
    model = [float(0.5 * x @ hvp(x) - b @ x)
             for x, _ in (conjugate_gradient(hvp, b, iterations=i) for i in range(1, 6))]
    assert model[0] < 0
    assert all(later <= earlier + 1e-12 for earlier, later in zip(model, model[1:]))


def fake_batch(k: int = 3, e: int = 2, t: int = 5) -> tuple[TensorDict, torch.Tensor]:
    torch.manual_seed(3)
    done = torch.zeros(k, e, t, dtype=torch.bool)
    done[..., -1] = True
    done[0, 0, 2] = True
    data = TensorDict(
        {
            "observation": torch.randn(k, e, t, 2),
            "action": torch.randn(k, e, t, 2),
            "mask": valid_mask(done),
        },
        [k, e, t],
    )
    return data, torch.randn(k, e, t)


def test_batched_inner_step_equals_per_task_loop() -> None:
    leader = MAMLTRPOLeader(PointNavigationCollector(episodes=2),
                            options=MamlTrpoOptions(hidden_sizes=(8, 8)))
    data, advantages = fake_batch()
    adapted = leader.adapt(leader.theta(), data, advantages, create_graph=True)
    queries = torch.randn(3, 7, 2)
    meta_loss = loc_scale(leader.net, adapted, queries)[0].square().sum()
    meta_grad = torch.autograd.grad(meta_loss, list(leader.net.parameters()))

    looped_loss = torch.zeros(())
    for k in range(3):
        loc, scale = leader.net(data["observation"][k])
        logp = log_prob(loc, scale, data["action"][k])
        loss = -episode_mean((logp * advantages[k])[None], data["mask"][k][None])[0]
        grads = torch.autograd.grad(loss, list(leader.net.parameters()), create_graph=True)
        task = {name: p - 0.1 * g for (name, p), g in zip(leader.net.named_parameters(), grads)}
        for name, value in task.items():
            torch.testing.assert_close(adapted[name][k], value)
        query_loc = functional_call(leader.net, task, (queries[k],))[0]
        looped_loss = looped_loss + query_loc.square().sum()
    looped_grad = torch.autograd.grad(looped_loss, list(leader.net.parameters()))
    for batched, looped in zip(meta_grad, looped_grad):
        torch.testing.assert_close(batched, looped, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("batch", [(), (4,), (4, 5)])
def test_per_task_policy_equals_each_tasks_network(batch: tuple[int, ...]) -> None:
    """``loc_scale``'s batched products are task ``k``'s network with ``params[k]``."""
    torch.manual_seed(3)
    net = GaussianMLP()
    params = TensorDict.from_module(net).detach().expand(3).clone()
    params = params.apply(lambda p: p + 0.3 * torch.randn_like(p)).flatten_keys(".").to_dict()
    observation = torch.randn(3, *batch, 2)
    loc, scale = loc_scale(net, params, observation)
    for k in range(3):
        task = {name: value[k] for name, value in params.items()}
        expected = functional_call(net, task, (observation[k],))
        torch.testing.assert_close(loc[k], expected[0])
        torch.testing.assert_close(scale[k], expected[1])


@pytest.mark.parametrize("batch", [(3,), (3, 4), (3, 4, 5)])
@pytest.mark.parametrize("per_task", [False, True])
def test_gaussian_actor_equals_the_probabilistic_actor(batch, per_task) -> None:
    """The collectors' actor writes what ``make_actor``'s ProbabilisticActor writes, acting at
    random: the same keys, the same values bit for bit from the same draws, and the same RNG
    state after."""
    net = GaussianMLP()
    with torch.no_grad():
        net.log_std.copy_(torch.tensor([-0.7, 0.4]))  # a scale other than 1 enters the density
    params = None
    if per_task:
        params = TensorDict.from_module(net).detach().expand(batch[0]).clone()
        params.apply_(lambda p: p + 0.1 * torch.randn_like(p))
    observation = torch.randn(*batch, 2)
    outputs = []
    for actor in (make_actor(net, params), GaussianActor(net, params)):
        torch.manual_seed(5)
        with set_exploration_type(ExplorationType.RANDOM):
            acted = actor(TensorDict({"observation": observation}, batch))
        outputs.append((acted, torch.rand(3)))
    (expected, expected_next), (acted, acted_next) = outputs
    assert set(acted.keys(True, True)) == set(expected.keys(True, True))
    for key in expected.keys(True, True):
        assert torch.equal(acted[key], expected[key]), key
    assert torch.equal(acted_next, expected_next)


def meta_hvp_pair(dtype: torch.dtype, hidden: tuple[int, ...] = (8, 8)):
    """The fast meta-KL Hessian-vector product and the plain double-backward reference, at the
    adapted policies of a small leader on fake data, with task weights."""
    leader = MAMLTRPOLeader(PointNavigationCollector(episodes=2),
                            options=MamlTrpoOptions(hidden_sizes=hidden))
    leader.net.to(dtype)
    train, train_advantages = fake_batch()
    valid, _ = fake_batch()
    train, valid = train.to(dtype), valid.to(dtype)
    train_advantages = train_advantages.to(dtype)
    valid["log_prob"] = torch.zeros(valid.batch_size, dtype=dtype)
    weights = torch.tensor([0.5, 0.3, 0.2], dtype=dtype)
    params = list(leader.net.parameters())
    names = [name for name, _ in leader.net.named_parameters()]
    broadcast, adapted = leader.inner_step(leader.theta(), train, train_advantages, True)
    leaves = [a.detach().requires_grad_(True) for a in adapted.values()]
    outputs = loc_scale(leader.net, dict(zip(names, leaves)), valid["observation"])
    current = tuple(o.detach() for o in outputs)

    def weighted_kl_of_outputs(outs: list[torch.Tensor]) -> torch.Tensor:
        return (weights * episode_mean(kl_divergence(*outs, *current), valid["mask"])).sum()

    def weighted_kl(parameters: list[torch.Tensor]) -> torch.Tensor:
        kl = leader.outer_terms(dict(zip(names, parameters)), valid, torch.zeros(3, 2, 5))[1]
        return (weights * kl).sum()

    structured = meta_kl_hessian_vector_product(
        weighted_kl_of_outputs, outputs, leaves, list(broadcast.values()),
        list(adapted.values()), params, damping=0.0,
    )
    # reference: differentiate ∇_θ KL(θ'(θ)) again, all the way through the inner step
    reference = kl_hessian_vector_product(weighted_kl(list(adapted.values())), params, damping=0.0)
    return leader, params, weighted_kl, structured, reference


@pytest.mark.parametrize(("dtype", "rtol", "atol"),
                         [(torch.float32, 1e-4, 1e-6), (torch.float64, 1e-6, 1e-12)])
def test_meta_kl_hessian_vector_product_equals_double_backward_through_adaptation(
    dtype: torch.dtype, rtol: float, atol: float
) -> None:
    leader, params, weighted_kl, structured, reference = meta_hvp_pair(dtype)
    size = sum(p.numel() for p in params)
    for seed in range(3):
        v = torch.randn(size, generator=torch.Generator().manual_seed(seed)).to(dtype)
        expected = reference(v)
        assert expected.norm() > 0
        torch.testing.assert_close(structured(v), expected, rtol=rtol, atol=atol)
    # the inner step matters: the KL Hessian of the unadapted policy is a different matrix
    first_order = kl_hessian_vector_product(
        weighted_kl([p.expand(3, *p.shape) for p in params]), params, damping=0.0
    )
    assert not torch.allclose(first_order(v), expected, rtol=1e-3, atol=1e-5)


def test_meta_kl_hessian_vector_product_equals_dense_hessian_on_a_tiny_net() -> None:
    leader, params, weighted_kl, structured, _ = meta_hvp_pair(torch.float64, hidden=(3,))
    names = [name for name, _ in leader.net.named_parameters()]
    train, train_advantages = fake_batch()
    train = train.to(torch.float64)
    theta0 = flatten(params).detach()

    def kl_of_theta(vector: torch.Tensor) -> torch.Tensor:
        theta = dict(zip(names, unflatten(vector, params)))
        adapted = leader.adapt(theta, train, train_advantages.double(), create_graph=True)
        return weighted_kl(list(adapted.values()))

    hessian = torch.autograd.functional.hessian(kl_of_theta, theta0)
    assert torch.linalg.eigvalsh(hessian).min() > -1e-10  # Σ_k J_k F_k J_k is PSD
    dense = torch.stack([structured(e) for e in torch.eye(theta0.numel(), dtype=torch.float64)])
    torch.testing.assert_close(dense, hessian, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("hvp_episodes", [None, 2])
def test_leader_kl_hessian_product_is_the_second_order_hessian_on_its_episodes(
    hvp_episodes: int | None,
) -> None:
    torch.manual_seed(6)
    collector = PointNavigationCollector(episodes=4, max_steps=10, seed=0)
    leader = MAMLTRPOLeader(
        collector, options=MamlTrpoOptions(hidden_sizes=(8, 8), hvp_episodes=hvp_episodes))
    batch = leader.collect(BoxUniform(SPACE).sample(3), create_graph=True)
    weights = torch.tensor([0.5, 0.3, 0.2])
    graph = leader.surrogate_gradient(batch, weights)[2]
    product = leader.kl_hessian_product(batch, weights, graph)

    # reference: double backpropagation of Σ_k w_k KL_k through an inner step taken on the
    # episodes the products use (all of them, or the first hvp_episodes)
    episodes = slice(0, hvp_episodes)
    params = list(leader.net.parameters())
    adapted = leader.adapt(leader.theta(), batch.train[:, episodes],
                           batch.train_advantages[:, episodes], create_graph=True)
    valid = batch.valid[:, episodes]
    loc, scale = loc_scale(leader.net, adapted, valid["observation"])
    kl = episode_mean(kl_divergence(loc, scale, loc.detach(), scale.detach()), valid["mask"])
    reference = kl_hessian_vector_product((weights * kl).sum(), params, leader.cg_damping)
    v = torch.randn(sum(p.numel() for p in params))
    expected = reference(v)
    assert (expected - leader.cg_damping * v).norm() > 0
    torch.testing.assert_close(product(v), expected, rtol=1e-4, atol=1e-6)


def test_line_search_takes_the_first_improving_step_inside_the_bound() -> None:
    def evaluate(theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return (theta - 1).square().mean(), theta.square().mean()

    theta0 = torch.zeros(5)
    new, accepted, loss, kl = backtracking_line_search(
        evaluate, theta0, -2 * torch.ones(5), torch.tensor(1.0), max_kl=1.0, max_steps=15, ratio=0.8
    )
    # 2·0.8^i must satisfy (2·0.8^i)² < 1: the first such i is 4
    assert accepted == 4
    torch.testing.assert_close(new, torch.full((5,), 2 * 0.8**4))
    assert all(map(torch.equal, (loss, kl), evaluate(new)))  # what the accepted step scored
    unchanged, none, loss, kl = backtracking_line_search(evaluate, theta0, 2 * torch.ones(5),
                                                         torch.tensor(1.0), max_kl=1.0)
    assert none is None and torch.equal(unchanged, theta0)
    assert loss.item() == 1.0 and kl.item() == 0.0  # θ and its loss unchanged


def test_trpo_update_improves_the_weighted_surrogate_within_the_kl_bound() -> None:
    torch.manual_seed(4)
    collector = PointNavigationCollector(episodes=4, max_steps=20, seed=0)
    leader = MAMLTRPOLeader(collector, options=MamlTrpoOptions(max_kl=1e-3))
    tasks = BoxUniform(SPACE).sample(3)
    batch = leader.collect(tasks, create_graph=True)
    weights = torch.tensor([0.7, 0.2, 0.1])
    with torch.no_grad():
        old = loc_scale(leader.net, batch.adapted, batch.valid["observation"])
    info = leader.trpo_update(batch, weights)
    assert info["trpo_line_search_steps"] >= 0

    adapted = leader.adapt(leader.theta(), batch.train, batch.train_advantages, create_graph=False)
    with torch.no_grad():
        loss, kl, _ = leader.outer_terms(adapted, batch.valid, batch.valid_advantages, old)
    assert 0 < (weights * kl).sum() <= 1e-3
    assert info["trpo_improvement"] > 0
    torch.testing.assert_close((weights * kl).sum().item(), info["trpo_kl"], rtol=1e-4, atol=1e-9)


def test_step_reports_per_task_returns_and_evaluate_keeps_theta() -> None:
    torch.manual_seed(5)
    leader = MAMLTRPOLeader(PointNavigationCollector(episodes=3, max_steps=10, seed=0))
    assert leader.on_policy
    tasks = BoxUniform(SPACE).sample(4)
    seen = []

    def erm(losses: torch.Tensor) -> torch.Tensor:
        seen.append(losses)
        return torch.full_like(losses, 0.25)

    batch = leader.collect(tasks, create_graph=True)
    out, scalars = leader.step(batch, erm)
    assert out.batch_size == (4,)
    torch.testing.assert_close(out["loss"], -out["return_post"])
    torch.testing.assert_close(seen[0], out["loss"])
    assert set(scalars) == {"trpo_kl", "trpo_improvement", "trpo_line_search_steps"}
    assert all(isinstance(value, float) for value in scalars.values())
    assert 0 <= scalars["trpo_kl"] <= leader.max_kl
    before = {k: v.clone() for k, v in leader.net.state_dict().items()}
    with torch.no_grad():
        fresh = leader.collect(tasks, PointNavigationCollector(episodes=2, max_steps=10))
        losses = leader.evaluate(fresh)
    assert fresh.valid.batch_size[:2] == (4, 2)
    assert losses.shape == (4,) and (losses > 0).all()
    torch.testing.assert_close(leader.evaluate(batch), out["loss"])  # the data, not θ, decide
    for key, value in leader.net.state_dict().items():
        assert torch.equal(value, before[key])


def test_short_seeded_run_improves_post_adaptation_return() -> None:
    torch.manual_seed(0)
    collector = PointNavigationCollector(episodes=10, max_steps=50, seed=0)
    leader = MAMLTRPOLeader(collector)
    sampler = BoxUniform(SPACE)
    test_tasks = sampler.sample(10)

    def erm(losses: torch.Tensor) -> torch.Tensor:
        return torch.full_like(losses, 1.0 / losses.numel())

    def mean_return() -> torch.Tensor:
        with torch.no_grad():
            return -leader.evaluate(leader.collect(test_tasks)).mean()

    before = mean_return()
    for _ in range(6):
        leader.step(leader.collect(sampler.sample(5), create_graph=True), erm)
    after = mean_return()
    assert after > before + 0.25 * before.abs()


@pytest.mark.parametrize(
    ("key", "kwargs"),
    [
        ("inner_lr", {"inner_lr": 0.0}),
        ("max_kl", {"max_kl": -1.0}),
        ("gamma", {"gamma": 1.5}),
        ("ls_backtrack_ratio", {"ls_backtrack_ratio": 1.0}),
        ("hvp_episodes", {"hvp_episodes": 0}),
    ],
)
def test_bad_hyper_parameters_raise_config_error(key: str, kwargs: dict) -> None:
    with pytest.raises(ConfigError, match=f"learner.maml_trpo.{key}"):
        MamlTrpoOptions(**kwargs)


def test_trpo_surrogate_at_the_sampling_policy_is_the_policy_gradient_and_the_kl_is_flat():
    """At π_θ = q the surrogate −mean(π_θ/q·Â) equals −mean(Â) and its gradient is that of the
    policy-gradient loss −mean(ln π_θ·Â) (Schulman et al. 2015: the surrogate matches the
    objective to first order); the mean KL is zero there, with zero gradient."""
    torch.manual_seed(0)
    loc = torch.randn(3, 2, 5, 2, dtype=torch.float64, requires_grad=True)
    log_scale = torch.randn(2, dtype=torch.float64, requires_grad=True)
    scale = log_scale.exp().expand_as(loc)
    action = torch.randn(3, 2, 5, 2, dtype=torch.float64)
    advantages = torch.randn(3, 2, 5, dtype=torch.float64)
    mask = torch.arange(5) < torch.randint(1, 6, (3, 2, 1))
    logp = log_prob(loc, scale, action)
    surrogate = surrogate_loss(logp, logp.detach(), advantages, mask)
    torch.testing.assert_close(surrogate, -episode_mean(advantages, mask))
    by_ratio = torch.autograd.grad(surrogate.sum(), [loc, log_scale], retain_graph=True)
    by_score = torch.autograd.grad(-episode_mean(logp * advantages, mask).sum(), [loc, log_scale],
                                   retain_graph=True)
    for a, b in zip(by_ratio, by_score):
        torch.testing.assert_close(a, b)
    kl = mean_kl(loc, scale, loc.detach(), scale.detach(), mask)
    torch.testing.assert_close(kl, torch.zeros(3, dtype=torch.float64))
    for g in torch.autograd.grad(kl.sum(), [loc, log_scale]):
        torch.testing.assert_close(g, torch.zeros_like(g))
    moved = mean_kl(loc.detach() + 0.1, scale.detach(), loc.detach(), scale.detach(), mask)
    assert (moved > 0).all()


def test_last_step_loss_reads_each_episodes_last_step():
    """−(the forward reward at each episode's last step), averaged over a task's episodes: an
    episode that ended early (mask) is read at its own last step."""
    forward = torch.arange(2 * 2 * 4, dtype=torch.float32).reshape(2, 2, 4, 1)
    mask = torch.ones(2, 2, 4, dtype=torch.bool)
    mask[1, 0, 2:] = False  # task 1's first episode ends after 2 steps
    trajectories = TensorDict({"reward_forward": forward, "mask": mask}, [2, 2, 4])
    # task 0: steps 3 and 7; task 1: steps 9 (episode 0, step 1) and 15
    assert torch.equal(last_step_loss(trajectories), -torch.tensor([5.0, 12.0]))


def test_mpts_with_the_authors_label_learns_from_the_last_step_loss():
    """risk.mpts.label=last_step: the principle's update reads the step's ``last_step_loss``,
    not its task loss."""
    from armeta_rl.trainers.game import GameTrainer

    players = players_of(compose_train(
        "benchmark=half_cheetah_vel", "method=mpts_maml", "risk.mpts.label=last_step",
        "trainer.meta_batch=3", "benchmark.collector.episodes=2",
        "benchmark.collector.max_steps=5", "risk.mpts.warmup=0"))
    principle, leader, seen, scored = players.principle, players.leader, [], []
    update, scores = principle.update, leader.scores
    principle.update = lambda tasks, losses: seen.append(losses) or update(tasks, losses)
    leader.scores = lambda batch: scored.append(scores(batch)) or scored[-1]
    options = TrainerConfig(iterations=1, meta_batch=3, progress=False)
    GameTrainer(leader, principle, options).train_iteration()
    assert principle.label == "last_step_loss"
    assert torch.equal(seen[0], scored[0]["last_step_loss"])
    assert not torch.equal(seen[0], scored[0]["loss"])
