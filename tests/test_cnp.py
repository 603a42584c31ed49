"""The CNP leader: shapes, likelihood, batching over tasks, weighted updates, training."""

from __future__ import annotations

import io
import math

import pytest
import torch
from tensordict import TensorDict

from armeta_rl.collectors.regression import SinusoidCollector
from armeta_rl.errors import ConfigError
from armeta_rl.learners.base import Leader
from armeta_rl.learners.cnp import CNPLeader, CnpOptions, gaussian_nll
from armeta_rl.tasks import BoxUniform, TaskSpace

SINUSOID = TaskSpace(("amplitude", "phase"), (0.1, 0.0), (5.0, math.pi))


def random_data(tasks: int, support: int, query: int, x_dim: int, y_dim: int) -> TensorDict:
    def points(n: int) -> dict[str, torch.Tensor]:
        return {"x": torch.randn(tasks, n, x_dim), "y": torch.randn(tasks, n, y_dim)}

    return TensorDict({"support": points(support), "query": points(query)}, batch_size=[tasks])


def uniform(losses: torch.Tensor) -> torch.Tensor:
    return torch.full_like(losses, 1.0 / losses.numel())


def test_shapes_on_sinusoid_tasks():
    torch.manual_seed(0)
    leader = CNPLeader(1, 1, SinusoidCollector(n_support=5, n_query=7))
    assert isinstance(leader, Leader) and leader.metric == "mse"
    tasks = BoxUniform(SINUSOID).sample(6)
    data = leader.collect(tasks)
    mean, std = leader.predict(data)
    assert mean.shape == std.shape == (6, 7, 1)
    assert bool((std >= 0.1).all())
    logs, scalars = leader.step(data, uniform)
    assert logs.batch_size == torch.Size([6]) and scalars == {}
    assert logs["loss"].shape == logs["mse"].shape == (6,)
    assert not logs["loss"].requires_grad and bool(logs["loss"].isfinite().all())
    assert leader.evaluate(data).shape == (6,)
    larger = leader.collect(tasks, SinusoidCollector(n_support=10, n_query=50))
    assert larger["query", "x"].shape == (6, 50, 1)
    assert leader.evaluate(larger).shape == (6,)


def test_shapes_with_vector_inputs_and_outputs():
    torch.manual_seed(1)
    data = random_data(4, 6, 9, 3, 2)
    leader = CNPLeader(3, 2, SinusoidCollector(), CnpOptions(hidden=32))
    mean, std = leader.predict(data)
    assert mean.shape == std.shape == (4, 9, 2)
    assert leader.evaluate(data).shape == (4,)


def test_gaussian_nll_matches_torch_normal_log_prob():
    torch.manual_seed(2)
    mean, target = torch.randn(5, 8, 2), 3 * torch.randn(5, 8, 2)
    std = 0.1 + torch.rand(5, 8, 2) * 2
    expected = -torch.distributions.Normal(mean, std).log_prob(target)
    assert torch.allclose(gaussian_nll(mean, std, target), expected, atol=1e-5)

    data = random_data(5, 4, 8, 1, 1)
    leader = CNPLeader(1, 1, SinusoidCollector())
    mean, std = leader.predict(data)
    reference = -torch.distributions.Normal(mean, std).log_prob(data["query", "y"]).mean((-2, -1))
    losses, squared_error = leader.task_losses(data)
    assert torch.allclose(losses, reference, atol=1e-5)
    assert torch.allclose(squared_error, (mean - data["query", "y"]).square().mean((-2, -1)))


def test_batched_prediction_equals_a_per_task_loop():
    torch.manual_seed(3)
    data = random_data(7, 5, 6, 1, 1)
    leader = CNPLeader(1, 1, SinusoidCollector())
    mean, std = leader.predict(data)
    losses, _ = leader.task_losses(data)
    for k in range(7):
        one = data[k:k + 1]
        mean_k, std_k = leader.predict(one)
        assert torch.allclose(mean[k:k + 1], mean_k, atol=1e-6)
        assert torch.allclose(std[k:k + 1], std_k, atol=1e-6)
        assert torch.allclose(losses[k:k + 1], leader.task_losses(one)[0], atol=1e-6)


def test_prediction_depends_on_the_support_set_not_its_order():
    torch.manual_seed(4)
    data = random_data(3, 6, 5, 1, 1)
    leader = CNPLeader(1, 1, SinusoidCollector())
    mean, _ = leader.predict(data)
    shuffled = data.clone()
    order = torch.randperm(6)
    shuffled["support", "x"] = data["support", "x"][:, order]
    shuffled["support", "y"] = data["support", "y"][:, order]
    assert torch.allclose(leader.predict(shuffled)[0], mean, atol=1e-6)
    changed = data.clone()
    changed["support", "y"] = data["support", "y"] + 1.0
    assert not torch.allclose(leader.predict(changed)[0], mean, atol=1e-4)


def test_step_minimizes_the_weighted_task_losses():
    """With all weight on task 0 the update ignores the other tasks; with uniform weights not."""
    torch.manual_seed(5)
    data = random_data(4, 5, 5, 1, 1)
    other = data.clone()
    other[1:] = random_data(3, 5, 5, 1, 1)
    only_first = torch.tensor([1.0, 0.0, 0.0, 0.0])

    def first_task(losses: torch.Tensor) -> torch.Tensor:
        assert not losses.requires_grad
        return only_first

    def after_step(batch: TensorDict, weights) -> list[torch.Tensor]:
        torch.manual_seed(6)
        leader = CNPLeader(1, 1, SinusoidCollector())
        leader.step(batch, weights)
        return [p.detach().clone() for p in leader.model.parameters()]

    same = zip(after_step(data, first_task), after_step(other, first_task), strict=True)
    assert all(torch.equal(a, b) for a, b in same)
    differ = zip(after_step(data, uniform), after_step(other, uniform), strict=True)
    assert not all(torch.equal(a, b) for a, b in differ)


def test_state_dict_restores_network_and_adam():
    """A checkpoint written with torch.save resumes exactly: same parameters, same Adam moments."""
    torch.manual_seed(7)
    data = random_data(4, 5, 5, 1, 1)
    trained = CNPLeader(1, 1, SinusoidCollector())
    for _ in range(5):
        trained.step(data, uniform)
    checkpoint = io.BytesIO()
    torch.save(trained.state_dict(), checkpoint)
    checkpoint.seek(0)
    restored = CNPLeader(1, 1, SinusoidCollector())
    restored.load_state_dict(torch.load(checkpoint))
    for leader in (trained, restored):
        leader.step(data, uniform)
    pairs = zip(trained.model.parameters(), restored.model.parameters(), strict=True)
    assert all(torch.equal(a, b) for a, b in pairs)


@pytest.mark.parametrize(("key", "kwargs"), [
    ("learner.cnp.likelihood", {"likelihood": "laplace"}),
    ("learner.cnp.lr", {"lr": 0.0}),
    ("learner.cnp.hidden", {"hidden": 0}),
])
def test_bad_config_is_rejected(key, kwargs):
    with pytest.raises(ConfigError) as error:
        CnpOptions(**kwargs)
    assert error.value.key == key


def train_on_sinusoids(likelihood: str, steps: int) -> tuple[TensorDict, TensorDict]:
    """Held-out (loss, mse) per task (10 support, 50 query points) before and after training."""
    torch.manual_seed(0)
    p0 = BoxUniform(SINUSOID)
    leader = CNPLeader(1, 1, SinusoidCollector(n_support=10, n_query=10),
                       CnpOptions(likelihood=likelihood))
    held_out, evaluation = p0.sample(64), SinusoidCollector(n_support=10, n_query=50)

    def score() -> TensorDict:
        torch.manual_seed(123)
        data = leader.collect(held_out, evaluation)
        mse = leader.evaluate(data)
        with torch.no_grad():
            loss, _ = leader.task_losses(data)
        return TensorDict({"loss": loss.mean(), "mse": mse.mean()})

    before = score()
    for _ in range(steps):
        leader.step(leader.collect(p0.sample(16)), uniform)
    return before, score()


def test_short_training_with_the_mse_option_halves_the_query_mse():
    before, after = train_on_sinusoids("mse", 500)
    assert after["mse"] < 0.5 * before["mse"]


def test_short_training_with_the_gaussian_likelihood_lowers_nll_and_mse():
    """The NLL halves within a few hundred steps (mostly by widening σ); the MSE follows slowly."""
    before, after = train_on_sinusoids("gaussian", 300)
    assert after["loss"] < 0.5 * before["loss"]
    assert after["mse"] < before["mse"]
