"""TaskSampler: shapes, ascent toward high-loss tasks, equality with AdversarialPrinciple's follower
update, bad input."""

from __future__ import annotations

import copy

import pytest
import torch

from armeta_rl.adversary import FlowAdversary, TaskSampler
from armeta_rl.errors import ConfigError, TrainingDiverged
from armeta_rl.risk.adversarial import AdversarialPrinciple, ArOptions
from armeta_rl.tasks import BoxUniform, TaskSpace

SPACE = TaskSpace(["torso_mass", "friction"], [0.5, 0.2], [2.0, 1.5])


def make_adversary(seed: int = 0, flow: str = "spline") -> FlowAdversary:
    torch.manual_seed(seed)
    return FlowAdversary(SPACE, BoxUniform(SPACE), flow)


def test_sample_and_update_shapes():
    sampler = TaskSampler(make_adversary())
    tasks = sampler.sample(7)
    assert tasks["params"].shape == (7, 2) and tasks["log_prob"].shape == (7,)
    assert SPACE.contains(tasks["params"].double()).all()
    stats = sampler.update(tasks, tasks["params"][:, 0])
    assert set(stats) == {"objective", "loss_mean", "entropy", "kl_p0", "lr", "grad_norm"}
    assert all(isinstance(v, float) and torch.isfinite(torch.tensor(v)) for v in stats.values())
    # the update accepts the params themselves, as a tensor
    sampler.update(tasks["params"], tasks["params"][:, 1])


def test_update_moves_mass_toward_high_loss_tasks():
    """With L(τ) = friction, ascent moves p_φ's mean friction up from the uniform 0.85."""
    torch.manual_seed(0)
    sampler = TaskSampler(make_adversary(flow="planar"), lr=3e-2)
    for _ in range(60):
        tasks = sampler.sample(64)
        sampler.update(tasks, tasks["params"][:, 1])
    friction = sampler.sample(4000)["params"][:, 1]
    assert friction.mean() > 0.85 + 0.15
    assert sampler.adversary.kl_from(sampler.adversary.base, 4000)[0] > 0.05


@pytest.mark.parametrize("lam,baseline", [(0.0, "mean"), (0.2, "leave_one_out")])
def test_update_equals_adversarial_principle_follower_update(lam, baseline):
    """Three updates of the sampler and of AdversarialPrinciple, from the same φ, tasks, losses
    and random streams, give bit-identical φ and statistics."""
    adversary = make_adversary(seed=1)
    sampler = TaskSampler(copy.deepcopy(adversary), lam=lam, lr=1e-2, total_updates=5,
                          baseline=baseline, initial_samples=32)
    principle = AdversarialPrinciple(
        copy.deepcopy(adversary),
        ArOptions(lam=lam, lr=1e-2, baseline=baseline, initial_samples=32),
        total_updates=5,
    )
    for step in range(3):
        torch.manual_seed(100 + step)
        tasks = sampler.sample(16)
        losses = (tasks["params"].double() - torch.tensor([2.0, 0.2])).pow(2).sum(-1)
        torch.manual_seed(step)
        ours = sampler.update(tasks, losses)
        torch.manual_seed(step)
        theirs = principle.update(tasks, losses)
        for key in ("objective", "entropy", "kl_p0", "lr", "grad_norm"):
            assert ours[key] == theirs[f"adversary/{key}"]
        for a, b in zip(sampler.adversary.parameters(), principle.adversary.parameters(),
                        strict=True):
            assert torch.equal(a, b)
    assert not all(torch.equal(a, b) for a, b in zip(sampler.adversary.parameters(),
                                                     adversary.parameters()))


def test_bad_input():
    sampler = TaskSampler(make_adversary())
    tasks = sampler.sample(4)
    with pytest.raises(ValueError, match=r"'losses' has shape \(3,\)"):
        sampler.update(tasks, torch.zeros(3))
    before = [p.clone() for p in sampler.adversary.parameters()]
    with pytest.raises(TrainingDiverged, match="non-finite losses"):
        sampler.update(tasks, torch.tensor([1.0, float("nan"), 0.0, 0.0]))
    assert all(torch.equal(a, b) for a, b in zip(before, sampler.adversary.parameters()))
    with pytest.raises(ConfigError, match="'total_updates' = 0"):
        TaskSampler(make_adversary(), total_updates=0)
    with pytest.raises(ConfigError, match="'n' = 0"):
        sampler.sample(0)


@pytest.mark.parametrize(("name", "value"), [
    ("lam", -1.0), ("lam", float("inf")), ("lr", 0.0), ("lr", 2.0), ("grad_clip", 0.0),
    ("baseline", "median"), ("initial_samples", 0), ("initial_samples", True),
])
def test_the_sampler_refuses_what_risk_ar_refuses_naming_its_argument(name, value):
    """risk.ar's ranges (ArOptions) are the sampler's: the same refusal, keyed by the argument."""
    with pytest.raises(ConfigError) as ours:
        TaskSampler(make_adversary(), **{name: value})
    with pytest.raises(ConfigError) as theirs:
        ArOptions(**{name: value})
    assert (ours.value.key, ours.value.allowed) == (name, theirs.value.allowed)
    assert theirs.value.key == f"risk.ar.{name}"
