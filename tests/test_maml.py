"""Batched MAML: the vmapped and the low-rank meta-batch equal a per-task loop, and the
meta-gradient equals finite differences of the adapted loss."""

import math

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torch.func import functional_call

from armeta_rl.collectors.regression import SinusoidCollector
from armeta_rl.errors import ConfigError
from armeta_rl.learners.maml import ADAPTATIONS, MAMLLeader, MamlOptions
from armeta_rl.learners.mlp import make_mlp
from armeta_rl.tasks import BoxUniform, TaskSpace

SPACE = TaskSpace(["amplitude", "phase"], [0.1, 0.0], [5.0, math.pi])


def make_leader(first_order=False, inner_steps=1, hidden=(128, 128, 128), adaptation="vmap"):
    torch.manual_seed(0)
    return MAMLLeader(
        make_mlp(1, 1, hidden),
        SinusoidCollector(5, 5),
        MamlOptions(inner_lr=0.01, inner_steps=inner_steps, first_order=first_order,
                    adaptation=adaptation),
    )


def per_task_loss(leader, params, task):
    """Plain-autograd reference for one task (no torch.func)."""
    support, query = task["support"], task["query"]
    names = list(params)
    for _ in range(leader.inner_steps):
        loss = (functional_call(leader.model, params, (support["x"],)) - support["y"]).pow(2).mean()
        grads = torch.autograd.grad(
            loss, [params[n] for n in names], create_graph=not leader.first_order
        )
        params = {n: params[n] - leader.inner_lr * g for n, g in zip(names, grads)}
    return (functional_call(leader.model, params, (query["x"],)) - query["y"]).pow(2).mean()


@pytest.mark.parametrize("adaptation", ADAPTATIONS)
@pytest.mark.parametrize("first_order,inner_steps", [(False, 1), (True, 1), (False, 2), (True, 2)])
def test_batched_maml_equals_per_task_loop(first_order, inner_steps, adaptation):
    leader = make_leader(first_order, inner_steps, adaptation=adaptation)
    torch.manual_seed(1)
    data = leader.collector.collect(BoxUniform(SPACE).sample(6))
    theta = dict(leader.model.named_parameters())

    batched = leader.task_losses(data)
    batched_grads = torch.autograd.grad(batched.mean(), list(theta.values()))

    looped = torch.stack([per_task_loss(leader, theta, data[k]) for k in range(6)])
    looped_grads = torch.autograd.grad(looped.mean(), list(theta.values()))

    torch.testing.assert_close(batched, looped, atol=1e-5, rtol=1e-5)
    for got, want in zip(batched_grads, looped_grads):
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("adaptation", ADAPTATIONS)
def test_batched_maml_equals_per_task_loop_with_vector_inputs_and_outputs(adaptation):
    """Sys-id shapes: 4 inputs, 3 outputs, 10 support and 190 query points per task."""
    torch.manual_seed(5)
    leader = MAMLLeader(make_mlp(4, 3, (32, 32)), SinusoidCollector(5, 5),
                        MamlOptions(inner_lr=0.05, adaptation=adaptation))
    data = TensorDict(
        {
            part: {"x": torch.randn(3, n, 4), "y": torch.randn(3, n, 3)}
            for part, n in (("support", 10), ("query", 190))
        },
        batch_size=[3],
    )
    theta = dict(leader.model.named_parameters())
    batched = leader.task_losses(data)
    looped = torch.stack([per_task_loss(leader, theta, data[k]) for k in range(3)])
    torch.testing.assert_close(batched, looped, atol=1e-5, rtol=1e-5)
    for got, want in zip(
        torch.autograd.grad(batched.sum(), list(theta.values())),
        torch.autograd.grad(looped.sum(), list(theta.values())),
    ):
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("first_order,inner_steps", [(False, 1), (True, 1), (False, 3)])
def test_low_rank_adaptation_equals_vmap_in_double_precision(first_order, inner_steps):
    """The two batched implementations are the same function of θ: losses, meta-gradients and
    the gradient-free evaluation agree to rounding in float64."""
    results = []
    for adaptation in ADAPTATIONS:
        leader = make_leader(first_order, inner_steps, hidden=(32, 32), adaptation=adaptation)
        leader.model.double()
        torch.manual_seed(1)
        data = leader.collector.collect(BoxUniform(SPACE).sample(7)).double()
        losses = leader.task_losses(data)
        grads = torch.autograd.grad(losses.mean(), list(leader.model.parameters()))
        with torch.no_grad():
            scores = leader.task_losses(data)
        assert not scores.requires_grad
        results.append((losses, grads, scores))
    (losses, grads, scores), (low_losses, low_grads, low_scores) = results
    torch.testing.assert_close(low_losses, losses, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(low_scores, scores, atol=1e-12, rtol=1e-12)
    for got, want in zip(low_grads, grads):
        torch.testing.assert_close(got, want, atol=1e-12, rtol=1e-10)


def test_bad_adaptation_is_a_config_error():
    with pytest.raises(ConfigError, match="learner.maml.adaptation.*allowed: vmap, low_rank"):
        make_leader(adaptation="loop")
    sequential = nn.Sequential(nn.Linear(1, 8), nn.ReLU(), nn.Linear(8, 1))
    with pytest.raises(ConfigError, match="learner.maml.adaptation.*not a Sequential; use vmap"):
        MAMLLeader(sequential, SinusoidCollector(5, 5), MamlOptions(adaptation="low_rank"))


@pytest.mark.parametrize("out_features", [1, 3, 16])
def test_mlp_is_the_linear_relu_network_with_the_same_initial_draws(out_features):
    """make_mlp stores weights input-major but computes nn.Linear/ReLU layers, drawn alike, with
    the same gradients (the 8-unit layer and 3 outputs multiply zero-padded to 16 columns)."""
    torch.manual_seed(6)
    mlp = make_mlp(2, out_features, (16, 8))
    torch.manual_seed(6)
    reference = nn.Sequential(
        nn.Linear(2, 16), nn.ReLU(), nn.Linear(16, 8), nn.ReLU(), nn.Linear(8, out_features)
    )
    x = torch.randn(7, 5, 2)
    out, expected = mlp(x), reference(x)
    torch.testing.assert_close(out, expected)
    assert all(w.is_contiguous() for w in mlp.weights)
    out.pow(2).sum().backward()
    expected.pow(2).sum().backward()
    linears = [layer for layer in reference if isinstance(layer, nn.Linear)]
    for weight, bias, linear in zip(mlp.weights, mlp.biases, linears, strict=True):
        torch.testing.assert_close(weight.grad, linear.weight.grad.T)
        torch.testing.assert_close(bias.grad, linear.bias.grad)


def test_evaluate_equals_task_losses_and_keeps_no_graph():
    leader = make_leader()
    data = leader.collect(BoxUniform(SPACE).sample(5))
    expected = leader.task_losses(data)
    got = leader.evaluate(data)
    assert not got.requires_grad
    assert all(p.grad is None for p in leader.model.parameters())
    torch.testing.assert_close(got, expected.detach())


def test_evaluate_after_step_scores_that_steps_data_at_the_new_theta():
    """The follower's losses (paper Algorithm 1): the step's support and query data, passed in,
    are scored at θ_{t+1} without collecting again; a copy of the data scores the same."""
    leader = make_leader()
    data = leader.collect(BoxUniform(SPACE).sample(5))
    out, scalars = leader.step(data, lambda losses: torch.full_like(losses, 1 / len(losses)))
    assert scalars == {}
    after = leader.task_losses(data).detach()
    assert not torch.allclose(after, out["loss"])
    rng = torch.get_rng_state()
    torch.testing.assert_close(leader.evaluate(data), after)
    torch.testing.assert_close(leader.evaluate(data.clone()), after)
    assert torch.equal(torch.get_rng_state(), rng)


@pytest.mark.parametrize("adaptation", ADAPTATIONS)
def test_meta_gradient_matches_finite_differences(adaptation):
    leader = make_leader(hidden=(16, 16), adaptation=adaptation)
    leader.model.double()
    torch.manual_seed(2)
    data = leader.collector.collect(BoxUniform(SPACE).sample(4)).double()
    theta = {n: p.detach().clone().requires_grad_() for n, p in leader.model.named_parameters()}
    direction = {n: torch.randn_like(p) for n, p in theta.items()}

    loss = leader.task_losses(data, theta).mean()
    grads = torch.autograd.grad(loss, list(theta.values()))
    analytic = sum((g * direction[n]).sum() for g, n in zip(grads, theta))

    eps = 1e-5

    def shifted(sign):
        params = {n: (p + sign * eps * direction[n]).detach() for n, p in theta.items()}
        return leader.task_losses(data, params).mean()

    numeric = (shifted(1) - shifted(-1)) / (2 * eps)
    assert float(analytic) == pytest.approx(float(numeric), rel=1e-5)


def test_second_order_term_changes_the_meta_gradient():
    torch.manual_seed(3)
    data = SinusoidCollector(5, 5).collect(BoxUniform(SPACE).sample(5))
    grads = []
    for first_order in (False, True):
        leader = make_leader(first_order)
        loss = leader.task_losses(data).mean()
        grads.append(torch.autograd.grad(loss, list(leader.model.parameters())))
    assert not all(torch.allclose(a, b) for a, b in zip(*grads))


def test_step_uses_task_weights():
    """A weight vector on one task gives that task's meta-gradient alone."""
    leader = make_leader()
    data = leader.collect(BoxUniform(SPACE).sample(4))
    expected = torch.autograd.grad(leader.task_losses(data)[2], list(leader.model.parameters()))

    captured = {}

    def only_third(losses):
        captured["losses"] = losses
        return torch.tensor([0.0, 0.0, 1.0, 0.0])

    leader.optimizer = torch.optim.SGD(leader.model.parameters(), lr=1.0)
    before = [p.detach().clone() for p in leader.model.parameters()]
    out, _ = leader.step(data, only_third)
    for old, new, g in zip(before, leader.model.parameters(), expected):
        torch.testing.assert_close(old - new.detach(), g, atol=1e-6, rtol=1e-5)
    assert not captured["losses"].requires_grad
    torch.testing.assert_close(out["loss"], captured["losses"])
