"""ANIL (docs/adding-a-learner.md's worked example): its meta-gradient against the inner step
written out by hand, and a run through the real command line."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from armeta_rl.collectors.regression import SinusoidCollector
from armeta_rl.learners.anil import ANILLeader, AnilOptions, BodyHead
from armeta_rl.tasks import TASK_KEY

TRAIN = [sys.executable, "-c", "from armeta_rl.cli import train; train()"]
ROOT = Path(__file__).resolve().parents[1]


def closed_form_losses(leader: ANILLeader, data: TensorDict, first_order: bool) -> torch.Tensor:
    """Per-task adapted query MSE, task by task, with the head's inner step written out: for
    features φ = body(x), residuals r = φWᵀ + b − y over n points and m outputs,
    ∇_W L = 2/(nm)·rᵀφ and ∇_b L = 2/(nm)·Σ r."""
    body, head = leader.model.body, leader.model.head
    losses = []
    for task in range(data.batch_size[0]):
        xs, ys = data["support", "x"][task], data["support", "y"][task]
        xq, yq = data["query", "x"][task], data["query", "y"][task]
        features = body(xs)
        residual = features @ head.weight.T + head.bias - ys
        scale = 2.0 / residual.numel()
        grad_w, grad_b = scale * residual.T @ features, scale * residual.sum(0)
        if first_order:
            grad_w, grad_b = grad_w.detach(), grad_b.detach()
        weight = head.weight - leader.inner_lr * grad_w
        bias = head.bias - leader.inner_lr * grad_b
        losses.append((body(xq) @ weight.T + bias - yq).pow(2).mean())
    return torch.stack(losses)


@pytest.mark.parametrize("first_order", [False, True])
def test_meta_gradient_is_the_closed_form_head_step(first_order: bool) -> None:
    torch.manual_seed(0)
    collector = SinusoidCollector(n_support=5, n_query=7)
    leader = ANILLeader(BodyHead(1, 1, [8, 6]), collector,
                        AnilOptions(inner_lr=0.3, first_order=first_order))
    leader.model.double()
    tasks = torch.tensor([[1.0, 0.5], [3.0, 2.0], [4.5, 0.1]], dtype=torch.float64)
    data = collector.collect(TensorDict({TASK_KEY: tasks}, [3]))
    weights = torch.tensor([0.2, 0.5, 0.3], dtype=torch.float64)
    theta = list(leader.model.parameters())

    losses = leader.task_losses(data)
    reference = closed_form_losses(leader, data, first_order)
    torch.testing.assert_close(losses, reference, rtol=1e-12, atol=0)
    grads = torch.autograd.grad((weights * losses).sum(), theta)
    expected = torch.autograd.grad((weights * reference).sum(), theta)
    for got, want in zip(grads, expected, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
    # the body learns through the adapted head: its gradient is not zero
    assert grads[0].abs().max() > 1e-6


def test_the_inner_loop_moves_the_head_only() -> None:
    torch.manual_seed(1)
    collector = SinusoidCollector()
    leader = ANILLeader(BodyHead(1, 1, [16, 16]), collector, AnilOptions(inner_steps=2))
    data = collector.collect(TensorDict({TASK_KEY: torch.tensor([[2.0, 1.0]])}, [1]))
    theta = dict(leader.model.named_parameters())
    adapted = leader.adapt(theta, data["support", "x"][0], data["support", "y"][0])
    assert adapted.keys() == theta.keys()
    for name, value in adapted.items():
        assert torch.equal(value, theta[name]) == (not name.startswith("head.")), name


def test_anil_trains_with_a_risk_principle_from_the_command_line(tmp_path) -> None:
    run_dir = tmp_path / "run"
    result = subprocess.run(
        [*TRAIN, "method.learner=anil", "method.risk=dr", "trainer.iterations=2",
         "trainer.meta_batch=4", "eval.n_tasks=8", "trainer.progress=false", "logger=none",
         f"hydra.run.dir={run_dir}"],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr
    config = OmegaConf.load(run_dir / "config.yaml")
    assert (config.method.name, config.method.learner, config.method.risk) == (
        "dr_anil", "anil", "dr")
    report = json.loads((run_dir / "eval.json").read_text())
    assert report["metric"] == "mse" and math.isfinite(report["initial"]["mean"])
    checkpoint = sorted((run_dir / "checkpoints").iterdir())[-1]
    leader = json.loads((checkpoint / "manifest.json").read_text())["components"]["leader"]
    state = torch.load(checkpoint / leader["path"] / leader["files"][0], weights_only=True)
    # the sizes came from the sinusoid collector: x and y are scalars
    assert state["model"]["head.weight"].shape == (1, 128)


def test_the_guide_shows_the_shipped_code():
    """Every code block of docs/adding-a-learner.md but the commands is in the file it quotes."""
    page = (ROOT / "docs" / "adding-a-learner.md").read_text()
    sources = ("learners/anil.py", "factory.py", "config.py")
    shipped = {"python": "".join((ROOT / "armeta_rl" / name).read_text() for name in sources),
               "yaml": (ROOT / "configs" / "train.yaml").read_text()}
    blocks = re.findall(r"```(python|yaml)\n(.*?)```", page, re.S)
    assert len(blocks) == 6
    for language, block in blocks:
        assert block in shipped[language], block
