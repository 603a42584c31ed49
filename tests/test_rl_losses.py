"""TorchRL loss modules as meta-RL objectives: batched over tasks they equal a per-task loop of
the papers' formulas, in value and gradient; MAML-TRPO's inner step is TorchRL's A2CLoss; the
MAML-PPO leader's meta-gradient equals a per-task loop, its step lowers its objective, and a
resumed run ends exactly like an uninterrupted one."""

from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict
from torch.func import functional_call
from torchrl.objectives import A2CLoss, ClipPPOLoss

from armeta_rl.cli.jobs import make_job
from armeta_rl.collectors.episodes import PointNavigationCollector, valid_mask
from armeta_rl.errors import ConfigError
from armeta_rl.job import Job
from armeta_rl.learners.maml_ppo import MAMLPPOLeader, MamlPpoOptions
from armeta_rl.learners.maml_trpo import MAMLTRPOLeader, MamlTrpoOptions, MetaBatch
from armeta_rl.rl.baseline import episode_mean
from armeta_rl.rl.losses import (
    check_loss_module,
    clip_ppo_loss,
    per_task_objective,
    reinforce_loss,
)
from armeta_rl.rl.policy import GaussianMLP, log_prob, make_actor
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, compose_train, players_of, train_config

K, E, T = 3, 4, 6


def episodes(k: int = K, e: int = E, t: int = T) -> TensorDict:
    """Random episodes ``[k, e, t]`` with a ragged mask, sampling log-probs and advantages."""
    torch.manual_seed(5)
    done = torch.zeros(k, e, t, 1, dtype=torch.bool)
    done[..., -1, :] = True
    done[0, 1, 2] = done[2, 0, 0] = True
    return TensorDict({
        "observation": torch.randn(k, e, t, 2), "action": 0.3 * torch.randn(k, e, t, 2),
        "log_prob": torch.randn(k, e, t) - 1.0, "reward": torch.randn(k, e, t, 1),
        "done": done, "mask": valid_mask(done.squeeze(-1)),
    }, [k, e, t])


def task_params(net: GaussianMLP, k: int = K) -> TensorDict:
    """``k`` parameter sets near the network's, leaves with gradients."""
    params = TensorDict.from_module(net).detach().expand(k).clone()
    params = params.apply(lambda p: p + 0.2 * torch.randn_like(p))
    return params.apply(lambda p: p.requires_grad_(True))


def loop_reference(net, params, data, advantages, per_step):
    """Each task's loss by a loop over tasks: ``per_step(log π(a|s), k)`` under task k's
    parameters (through ``functional_call``), then its mean over the task's valid steps."""
    flat = params.flatten_keys(".")
    out = []
    for k in range(data.batch_size[0]):
        loc, scale = functional_call(net, {n: flat[n][k] for n in flat.keys(True, True)},
                                     (data["observation"][k],))
        logp = log_prob(loc, scale, data["action"][k])
        out.append(episode_mean(per_step(logp, k)[None], data["mask"][k][None])[0])
    return torch.stack(out)


def assert_same_value_and_gradient(batched, looped, params):
    torch.testing.assert_close(batched, looped)
    leaves = list(params.values(True, True))
    for g_b, g_l in zip(torch.autograd.grad(batched.sum(), leaves),
                        torch.autograd.grad(looped.sum(), leaves)):
        torch.testing.assert_close(g_b, g_l)


def test_a2c_loss_batched_over_tasks_is_reinforce_per_task():
    """TorchRL's A2CLoss with the data's advantages, over K tasks at once: −mean(log π·Â) of
    each task under its own parameters (Williams 1992; MAML Sec. 5.3)."""
    net, data = GaussianMLP(2, 2, (8, 8)), episodes()
    params, advantages = task_params(net), torch.randn(K, E, T)
    batched = per_task_objective(reinforce_loss(make_actor(net)), net, params, data, advantages)
    looped = loop_reference(net, params, data, advantages,
                            lambda logp, k: -logp * advantages[k])
    assert_same_value_and_gradient(batched, looped, params)


def test_clip_ppo_loss_batched_over_tasks_is_the_clipped_surrogate_per_task():
    """TorchRL's ClipPPOLoss over K tasks: −mean(min(r Â, clip(r, 1 ± ε) Â)) of each task, r the
    ratio to the sampling policy (PPO Eq. (7))."""
    net, data = GaussianMLP(2, 2, (8, 8)), episodes()
    params, advantages = task_params(net), torch.randn(K, E, T)
    loss = clip_ppo_loss(make_actor(net), clip_epsilon=0.1)
    batched = per_task_objective(loss, net, params, data, advantages)

    def clipped(logp, k):
        ratio = (logp - data["log_prob"][k]).exp()
        return -torch.min(ratio * advantages[k], ratio.clamp(0.9, 1.1) * advantages[k])

    assert_same_value_and_gradient(batched, loop_reference(net, params, data, advantages,
                                                           clipped), params)


def test_a_batched_loss_leaves_the_policy_network_as_it_was():
    """The network's own parameters (the same objects, still trainable) after a batched call."""
    net = GaussianMLP(2, 2, (8, 8))
    before = {name: p for name, p in net.named_parameters()}
    per_task_objective(reinforce_loss(make_actor(net)), net, task_params(net), episodes(),
                       torch.randn(K, E, T)).sum().backward()
    after = dict(net.named_parameters())
    assert all(after[n] is p and p.requires_grad and p.grad is None for n, p in before.items())


def test_a_loss_module_that_cannot_run_per_task_is_refused():
    net = GaussianMLP(2, 2, (8, 8))
    with pytest.raises(ValueError, match="functional=False"):
        check_loss_module(ClipPPOLoss(make_actor(net), None, critic_coeff=None), net)
    with pytest.raises(ValueError, match="leader's policy network"):
        check_loss_module(clip_ppo_loss(make_actor(GaussianMLP(2, 2, (8, 8)))), net)


def ppo_leader(**options) -> MAMLPPOLeader:
    torch.manual_seed(0)
    collector = PointNavigationCollector(episodes=3, max_steps=8)
    return MAMLPPOLeader(collector, MamlPpoOptions(hidden_sizes=[8, 8], **options))


def a_meta_batch(leader: MAMLPPOLeader) -> MetaBatch:
    tasks = TensorDict({"params": torch.tensor([[0.3, -0.2], [-0.4, 0.1], [0.0, 0.45]])}, [3])
    return leader.collect(tasks)


@pytest.mark.parametrize("first_order", [False, True])
def test_maml_ppo_meta_gradient_equals_a_per_task_loop(first_order):
    """∇_θ Σ_k w_k L^PPO_k(θ'_k(θ)) of the batched leader against a loop that adapts each task
    with its own inner REINFORCE step and scores it with the clipped surrogate."""
    leader = ppo_leader(first_order=first_order, clip_epsilon=0.1)
    batch = a_meta_batch(leader)
    weights = torch.tensor([0.5, 0.2, 0.3], dtype=torch.float64)
    theta = list(leader.net.parameters())
    batched = torch.autograd.grad(
        (weights * leader.outer_loss(batch).double()).sum(), theta)

    looped = torch.zeros((), dtype=torch.float64)
    names = [n for n, _ in leader.net.named_parameters()]
    for k in range(3):
        train, valid = batch.train[k], batch.valid[k]
        loc, scale = leader.net(train["observation"])
        inner = -episode_mean((log_prob(loc, scale, train["action"])
                               * batch.train_advantages[k])[None], train["mask"][None])[0]
        grads = torch.autograd.grad(inner, theta, create_graph=not first_order)
        adapted = {n: p - 0.1 * g for n, p, g in zip(names, theta, grads)}
        loc, scale = functional_call(leader.net, adapted, (valid["observation"],))
        ratio = (log_prob(loc, scale, valid["action"]) - valid["log_prob"]).exp()
        a = batch.valid_advantages[k]
        clipped = -torch.min(ratio * a, ratio.clamp(0.9, 1.1) * a)
        looped = looped + weights[k] * episode_mean(clipped[None], valid["mask"][None])[0]
    for g_b, g_l in zip(batched, torch.autograd.grad(looped, theta)):
        torch.testing.assert_close(g_b, g_l, rtol=1e-4, atol=1e-6)


def test_a_maml_ppo_step_lowers_its_objective_and_reports_the_adapted_returns():
    leader = ppo_leader(lr=3e-3, epochs=4)
    batch = a_meta_batch(leader)
    per_task, scalars = leader.step(batch, lambda losses: torch.full_like(losses, 1 / 3))
    assert scalars["ppo_objective_last"] < scalars["ppo_objective_first"]
    torch.testing.assert_close(per_task["return_post"], -per_task["loss"])
    assert per_task.batch_size == (3,)


def test_maml_ppo_is_a_learner_of_episodes_only():
    cfg = compose_train(*SMALL_RUN, "method.learner=maml_ppo")
    with pytest.raises(ConfigError, match="'method.learner' = 'maml_ppo': learns from episodes"):
        players_of(cfg)


PPO_RUN = (*SMALL_RUN, "benchmark=point_nav_plain", "method=ar_maml", "method.learner=maml_ppo",
           "trainer.meta_batch=3", "benchmark.collector.episodes=3",
           "benchmark.collector.max_steps=8", "eval.n_tasks=3", "learner.maml_ppo.epochs=2",
           "learner.maml_ppo.hidden_sizes=[8,8]", "trainer.iterations=4",
           "trainer.checkpoint_every=2")


def test_a_resumed_maml_ppo_run_ends_exactly_like_an_uninterrupted_one(tmp_path):
    """The outer optimizer's state travels in the checkpoint: AR-MAML-PPO stopped after
    iteration 2 and resumed writes the uninterrupted run's eval.json, byte for byte."""
    run_training(Job(train_config(*PPO_RUN), tmp_path / "whole"), progress=False)
    run_training(Job(train_config(*PPO_RUN, "trainer.stop_at=2"), tmp_path / "split"),
                 progress=False)
    run_training(make_job([f"resume={tmp_path / 'split'}"]), progress=False)
    whole, split = ((tmp_path / d / "eval.json").read_text() for d in ("whole", "split"))
    assert whole == split
    assert json.loads(whole)["method"] == "ar_maml_ppo"


def test_maml_trpo_takes_its_inner_step_with_a_torchrl_loss_module_any_can_replace():
    """MAML-TRPO's default inner objective is TorchRL's A2CLoss; a clipped PPO loss built on its
    policy takes its place and gives the clipped surrogate of each task."""
    collector = PointNavigationCollector(episodes=2)
    assert isinstance(MAMLTRPOLeader(collector, MamlTrpoOptions(hidden_sizes=[8, 8]))
                      .inner_objective, A2CLoss)
    leader = MAMLTRPOLeader(collector, MamlTrpoOptions(hidden_sizes=[8, 8]),
                            inner_loss=lambda actor: clip_ppo_loss(actor, clip_epsilon=0.1))
    data, advantages, params = episodes(), torch.randn(K, E, T), task_params(leader.net)

    def clipped(logp, k):
        ratio = (logp - data["log_prob"][k]).exp()
        return -torch.min(ratio * advantages[k], ratio.clamp(0.9, 1.1) * advantages[k])

    got = leader.inner_loss(params.flatten_keys(".").to_dict(), data, advantages)
    assert_same_value_and_gradient(got, loop_reference(leader.net, params, data, advantages,
                                                       clipped), params)
