"""Opt-in torch.compile of the hot paths: a compiled run computes what the eager run computes.

The ``aot_eager`` backend traces the same graphs as ``inductor`` (through vmap, grad and the
flow's couplings, forward and backward) without generating code, so these checks take seconds;
inductor's kernels are exercised by ``python -m benchmarks.timing bench_meta_iteration --compile``.
"""

import math

import pytest
import torch
from torch._dynamo.utils import counters

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.collectors.regression import SinusoidCollector
from armeta_rl.collectors.sysid import SysIdCollector
from armeta_rl.compiling import compile_backend
from armeta_rl.envs.acrobot import AcrobotEnv
from armeta_rl.envs.pendulum import PendulumEnv
from armeta_rl.errors import ConfigError
from armeta_rl.learners.maml import ADAPTATIONS, MAMLLeader, MamlOptions
from armeta_rl.learners.mlp import make_mlp, relu
from armeta_rl.risk.adversarial import AdversarialPrinciple, ArOptions
from armeta_rl.tasks import BoxUniform, TaskSpace

SPACE = TaskSpace(["amplitude", "phase"], [0.1, 0.0], [5.0, math.pi])


@pytest.mark.parametrize(("value", "backend"), [
    (False, None), (None, None), (True, "inductor"), ("aot_eager", "aot_eager"),
])
def test_compile_option_names_a_backend(value, backend):
    assert compile_backend("learner.maml.compile", value) == backend


@pytest.mark.parametrize("value", ["fast", 1, "yes"])
def test_bad_compile_option_names_its_key(value):
    with pytest.raises(ConfigError) as error:
        compile_backend("risk.ar.compile", value)
    assert error.value.key == "risk.ar.compile"


def test_traced_relu_equals_torch_relu_with_its_gradients():
    """Under tracing the MLP's ReLU is written (x + |x|) / 2: the same values and derivatives as
    torch.relu away from 0 (its second order runs inside the compiled MAML loss, checked below)."""
    x = torch.randn(257, dtype=torch.float64)
    x = torch.where(x.abs() < 1e-3, 1.0, x).requires_grad_()
    traced = torch.compile(relu, backend="aot_eager", fullgraph=True, dynamic=False)
    value, reference = traced(x), torch.relu(x)
    assert torch.equal(value, reference)
    weights = torch.randn_like(x)
    (grad,) = torch.autograd.grad((weights * value).sum(), x)
    (grad_ref,) = torch.autograd.grad((weights * reference).sum(), x)
    assert torch.equal(grad, grad_ref)


def train_leader(
    compile: bool | str, adaptation: str
) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Initial parameters, then losses and evaluations of three steps, then final parameters."""
    torch.manual_seed(0)
    leader = MAMLLeader(make_mlp(1, 1, (32, 32)), SinusoidCollector(5, 5),
                        MamlOptions(compile=compile, adaptation=adaptation))
    initial = [p.detach().clone() for p in leader.model.parameters()]
    tasks = BoxUniform(SPACE).sample(6)
    losses = []
    data = leader.collect(tasks)
    for _ in range(3):
        losses.append(leader.step(data, lambda x: torch.full_like(x, 1 / len(x)))[0]["loss"])
        losses.append(leader.evaluate(data))
    return initial, losses + [p.detach() for p in leader.model.parameters()]


@pytest.mark.parametrize("adaptation", ADAPTATIONS)
def test_compiled_maml_steps_equal_eager_steps(adaptation):
    initial, eager = train_leader(False, adaptation)
    counters.clear()
    _, compiled = train_leader("aot_eager", adaptation)
    assert counters["stats"]["unique_graphs"] >= 2  # the training and the no-grad evaluation
    torch.testing.assert_close(compiled, eager, rtol=1e-5, atol=1e-6)
    trained = eager[-len(initial):]
    assert all((p - q).abs().max() > 1e-4 for p, q in zip(trained, initial, strict=True))


def train_adversary(compile: bool | str) -> tuple[AdversarialPrinciple, list[torch.Tensor]]:
    torch.manual_seed(0)
    principle = AdversarialPrinciple(
        FlowAdversary(SPACE, BoxUniform(SPACE), "spline", hidden=8),
        ArOptions(lr=0.05, compile=compile),
    )
    proposed = []
    for _ in range(3):
        tasks = principle.propose(16)
        proposed += [tasks["params"], tasks["log_prob"]]
        principle.update(tasks, (tasks["params"] - torch.tensor([0.1, 0.0])).pow(2).sum(-1))
    return principle, proposed


def test_compiled_adversary_updates_equal_eager_updates():
    eager, eager_tasks = train_adversary(False)
    counters.clear()
    compiled, compiled_tasks = train_adversary("aot_eager")
    assert counters["stats"]["unique_graphs"] >= 2  # the log-density and the push-forward
    torch.testing.assert_close(compiled_tasks, eager_tasks, rtol=1e-9, atol=1e-10)
    for got, expected in zip(compiled.parameters(), eager.parameters(), strict=True):
        torch.testing.assert_close(got, expected, rtol=1e-9, atol=1e-10)
    moved = eager.adversary.log_prob(eager_tasks[0]) - eager_tasks[1]
    assert moved.abs().max() > 1e-3


@pytest.mark.parametrize("env", [PendulumEnv, AcrobotEnv])
def test_compiled_physics_collects_what_the_eager_physics_collects(env):
    """``benchmark.collector.compile``: the compiled equations of motion give the eager
    transitions, and follow each collection's new identifiers (none is baked into the graph);
    the acrobot's 200-step episodes go through its partial resets."""
    box = TaskSpace(["m1", "m2"] if env is AcrobotEnv else ["m", "l"], [0.4, 0.4], [1.6, 1.6])
    collected = {}
    for backend in (False, "aot_eager"):
        torch.manual_seed(0)
        collector = SysIdCollector(env, n_transitions=200, episodes=1, compile=backend)
        counters.clear()
        collected[backend] = [collector.collect(BoxUniform(box).sample(4)) for _ in range(3)]
        if backend:
            assert counters["stats"]["unique_graphs"] == 1
    for eager, compiled in zip(collected[False], collected["aot_eager"], strict=True):
        torch.testing.assert_close(compiled.to_dict(), eager.to_dict(), rtol=1e-6, atol=1e-6)
    first, second = (data["query", "y"] for data in collected[False][:2])
    assert (first - second).abs().max() > 1e-2
