"""TorchRL PPO on a MuJoCo task family: uniform, adversarial and risk-predictive domain
randomization.

Trains one PPO agent (ClipPPOLoss, GAE, ``torchrl.collectors.Collector``) per task source on the
physics family of a YAML file (default: HalfCheetah, torso mass scale × friction scale):

    uniform      every batch of episodes runs on physics drawn uniformly from the box
    adversarial  a flow adversary (:class:`armeta_rl.adversary.TaskSampler`) proposes the physics
                 of each batch and ascends on the negative returns of those episodes
    mpts, pdts   a risk predictive model picks each batch from a pseudo-batch of uniform draws
                 (MPTS's UCB score, PDTS's posterior sample and diversity) and learns from the
                 negative returns (:class:`armeta_rl.risk.PrincipleSampler`), with the settings of
                 the PDTS authors' domain-randomization code (see :func:`make_sampler`)

Both start from the same seed and are evaluated on the same held-out grid of the box (the cell
midpoints of a 5 × 5 grid, the mean of 4 deterministic episodes each): mean return, CVaR0.5 (the
mean of the lowest half of the cell returns) and the worst cell. Results go to
``<out>/results.json``, the policies to ``<out>/actor_<source>_seed<seed>.pt``.

    python examples/ppo_domain_randomization.py --quick        # seconds: a smoke run
    python examples/ppo_domain_randomization.py --out runs/dr  # the full comparison

Each iteration draws one task per sub-env (``--tasks``), resets the collector's env with them
(``collector.reset(tensordict=...)``; the identifiers are kept across the automatic resets inside
the batch) and collects ``tasks × episode_steps`` frames: one episode per task. The adversary's
loss of a task is the negative return over ``episode_steps`` steps of its batch (for an env that
terminates early, the negative mean reward per step times ``episode_steps``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.envs import DoubleToFloat, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from armeta_rl.adversary import FlowAdversary, TaskSampler
from armeta_rl.envs.mujoco_tasks import TaskFamily, load_task_family, make_gym_task_env
from armeta_rl.risk import MPTSPrinciple, PDTSPrinciple, PrincipleSampler
from armeta_rl.risk.mpts import MptsOptions
from armeta_rl.risk.pdts import PdtsOptions
from armeta_rl.tasks import BoxUniform

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_FAMILY = ROOT / "configs" / "task_family" / "half_cheetah.yaml"
SOURCES = ("uniform", "adversarial", "mpts", "pdts")


@dataclass(frozen=True)
class Settings:
    """Sizes of one comparison (``--quick`` shrinks them to a smoke run)."""

    iterations: int = 300
    tasks: int = 16
    episode_steps: int = 200
    epochs: int = 10
    minibatch: int = 400
    lr: float = 3e-4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_epsilon: float = 0.2
    entropy_coeff: float = 1e-3
    hidden: int = 64
    adversary_lr: float = 3e-3
    adversary_lam: float = 0.0
    grid: int = 5
    eval_episodes: int = 4


QUICK = Settings(iterations=2, tasks=2, episode_steps=10, epochs=1, minibatch=10, grid=2,
                 eval_episodes=2)


def make_sampler(source: str, family: TaskFamily,
                 settings: Settings) -> TaskSampler | PrincipleSampler | None:
    """The task sampler of ``source`` (``None`` for uniform draws). MPTS and PDTS take the PDTS
    authors' domain-randomization settings: losses standardized per batch, 10 Adam steps at
    0.005 on one ELBO sample, uniform draws for the first tenth of training; MPTS a pool of
    2.5 × the batch, γ1 = 5 on 50 samples, half of the batch random; PDTS a pool of 64 × the
    batch, diversity γ = 1 measured in the unit box."""
    uniform = BoxUniform(family.space)
    if source == "adversarial":
        return TaskSampler(FlowAdversary(family.space, uniform), lam=settings.adversary_lam,
                           lr=settings.adversary_lr, total_updates=settings.iterations)
    shared = {"lr": 5e-3, "steps": 10, "elbo_samples": 1, "standardize": True,
              "warmup": settings.iterations // 10}
    if source == "mpts":
        return PrincipleSampler(MPTSPrinciple(uniform, MptsOptions(
            **shared, candidate_ratio=2.5, gamma_std=5.0, score_samples=50,
            random_fraction=0.5)))
    if source == "pdts":
        return PrincipleSampler(PDTSPrinciple(uniform, PdtsOptions(
            **shared, candidate_ratio=64.0, distance="unit")))
    return None


def make_env(family: TaskFamily, tasks: int, steps: int) -> TransformedEnv:
    """``tasks`` HalfCheetah-like sub-envs (SerialEnv), physics from ``"params"``, episodes
    truncated after ``steps`` steps, float32 observations and rewards."""
    env = make_gym_task_env(family, num_tasks=tasks, max_steps=steps)
    env.append_transform(DoubleToFloat())
    return env


def make_agent(env: TransformedEnv, hidden: int) -> tuple[ProbabilisticActor, ValueOperator]:
    """A tanh-Gaussian MLP policy and an MLP value function on the observation."""
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec.shape[-1]

    def mlp(out: int) -> nn.Sequential:
        return nn.Sequential(nn.Linear(obs_dim, hidden), nn.Tanh(), nn.Linear(hidden, hidden),
                             nn.Tanh(), nn.Linear(hidden, out))

    actor = ProbabilisticActor(
        TensorDictModule(nn.Sequential(mlp(2 * act_dim), NormalParamExtractor()),
                         in_keys=["observation"], out_keys=["loc", "scale"]),
        spec=env.action_spec,
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": env.action_spec.space.low[..., 0, :],
                             "high": env.action_spec.space.high[..., 0, :]},
        return_log_prob=True,
    )
    critic = ValueOperator(mlp(1), in_keys=["observation"])
    return actor, critic


def task_losses(batch: TensorDict, steps: int) -> torch.Tensor:
    """The adversary's loss of each sub-env's task ``[tasks]``: the negative return over
    ``steps`` steps (negative mean reward per step of its batch times ``steps``)."""
    return -batch["next", "reward"].squeeze(-1).to(torch.float64).mean(-1) * steps


def cvar(returns: torch.Tensor, alpha: float = 0.5) -> float:
    """CVaR_alpha of the returns: the mean of their lowest ``ceil(alpha · n)``."""
    k = max(1, math.ceil(alpha * returns.numel()))
    return float(returns.sort().values[:k].mean())


def evaluate(actor: ProbabilisticActor, family: TaskFamily, settings: Settings,
             seed: int) -> dict[str, object]:
    """Deterministic returns of ``actor`` on the grid midpoints of the box: each cell's return is
    the mean of ``eval_episodes`` episodes (from different initial states), all in one batch."""
    grid, _ = family.space.grid(settings.grid, torch.float64)
    episodes = settings.eval_episodes
    params = grid.to(torch.get_default_dtype()).repeat_interleave(episodes, 0)
    env = make_env(family, len(params), settings.episode_steps)
    env.set_seed(seed)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        start = env.reset(TensorDict({"params": params}, [len(params)]))
        rollout = env.rollout(settings.episode_steps, actor, auto_reset=False,
                              break_when_any_done=False, tensordict=start)
    env.close()
    episode_returns = rollout["next", "reward"].squeeze(-1).sum(-1).to(torch.float64)
    returns = episode_returns.reshape(len(grid), episodes).mean(-1)
    return {
        "mean_return": float(returns.mean()),
        "cvar_0.5": cvar(returns),
        "worst_cell": float(returns.min()),
        "worst_params": grid[int(returns.argmin())].tolist(),
        "grid_params": grid.tolist(),
        "grid_returns": returns.tolist(),
        "episode_returns": episode_returns.reshape(len(grid), episodes).tolist(),
    }


def train(source: str, family: TaskFamily, settings: Settings, seed: int, out: Path,
          log: Callable[[str], None] = print) -> dict[str, object]:
    """Train PPO with tasks from ``source`` (one of :data:`SOURCES`), save the policy to
    ``out/actor_<source>_seed<seed>.pt`` and evaluate it."""
    torch.manual_seed(seed)
    env = make_env(family, settings.tasks, settings.episode_steps)
    env.set_seed(seed)
    actor, critic = make_agent(env, settings.hidden)
    uniform = BoxUniform(family.space)
    sampler = make_sampler(source, family, settings)
    prefix = "adversary/" if isinstance(sampler, TaskSampler) else ""  # MPTS/PDTS: risk/…
    frames = settings.tasks * settings.episode_steps
    collector = Collector(env, actor, frames_per_batch=frames,
                          total_frames=frames * settings.iterations,
                          auto_register_policy_transforms=False)
    advantage = GAE(gamma=settings.gamma, lmbda=settings.gae_lambda, value_network=critic)
    loss = ClipPPOLoss(actor, critic, clip_epsilon=settings.clip_epsilon,
                       entropy_coeff=settings.entropy_coeff, normalize_advantage=True)
    optimizer = torch.optim.Adam(loss.parameters(), lr=settings.lr)
    buffer = ReplayBuffer(storage=LazyTensorStorage(frames), batch_size=settings.minibatch,
                          sampler=SamplerWithoutReplacement())
    history = []
    start = time.perf_counter()
    tasks = (sampler or uniform).sample(settings.tasks)
    collector.reset(tensordict=TensorDict({"params": tasks["params"]}, [settings.tasks]))
    for iteration, batch in enumerate(collector):
        losses = task_losses(batch, settings.episode_steps)
        stats = {} if sampler is None else sampler.update(tasks, losses)
        with torch.no_grad():
            advantage(batch)
        buffer.extend(batch.reshape(-1))
        for _ in range(settings.epochs):
            for minibatch in buffer:
                terms = loss(minibatch)
                total = terms["loss_objective"] + terms["loss_critic"] + terms["loss_entropy"]
                optimizer.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), 1.0)
                optimizer.step()
        collector.update_policy_weights_()
        elapsed = time.perf_counter() - start
        history.append({"iteration": iteration, "mean_return": float(-losses.mean()),
                        "seconds": elapsed,
                        **{f"{prefix}{k}": v for k, v in stats.items()}})
        log(f"[{source}] iteration {iteration + 1}/{settings.iterations}: mean return "
            f"{-losses.mean():.1f}, {elapsed / (iteration + 1):.2f} s/iteration")
        if iteration + 1 < settings.iterations:
            tasks = (sampler or uniform).sample(settings.tasks)
            collector.reset(tensordict=TensorDict({"params": tasks["params"]},
                                                  [settings.tasks]))
    collector.shutdown()
    result = {"train_seconds": time.perf_counter() - start, "history": history}
    torch.save(actor.state_dict(), out / f"actor_{source}_seed{seed}.pt")
    result["eval"] = evaluate(actor, family, settings, seed + 1)
    if isinstance(sampler, TaskSampler):
        result["adversary_samples"] = sampler.sample(256)["params"].tolist()
    return result


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smoke run of a few seconds")
    parser.add_argument("--family", default=str(DEFAULT_FAMILY), help="task-family YAML")
    parser.add_argument("--out", default="runs/ppo_domain_randomization", help="output folder")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="one run per seed")
    parser.add_argument("--iterations", type=int, default=None, help="override the iterations")
    parser.add_argument("--adversary-lam", type=float, default=None,
                        help="override λ, the weight of the adversary's KL(p0 ‖ p_φ) term")
    parser.add_argument("--sources", nargs="+", default=list(SOURCES), choices=SOURCES)
    return parser.parse_args(argv)


METRICS = ("mean_return", "cvar_0.5", "worst_cell")


def summary(runs: list[dict[str, object]]) -> dict[str, float]:
    """Each evaluation metric averaged over the seeds' runs, and the training time."""
    out = {m: sum(r["eval"][m] for r in runs) / len(runs) for m in METRICS}
    out["train_seconds"] = sum(r["train_seconds"] for r in runs) / len(runs)
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the comparison; exit code 2 with one line on a bad task family or setting."""
    args = parse_args(argv)
    settings = QUICK if args.quick else Settings()
    try:
        if args.iterations is not None:
            if args.iterations < 1:
                raise ValueError(f"'--iterations' = {args.iterations}: must be >= 1")
            settings = Settings(**{**asdict(settings), "iterations": args.iterations})
        if args.adversary_lam is not None:
            settings = Settings(**{**asdict(settings), "adversary_lam": args.adversary_lam})
        family = load_task_family(args.family)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        results = {"family": args.family, "env": family.env, "settings": asdict(settings),
                   "seeds": args.seeds, "runs": {s: [] for s in args.sources}, "summary": {}}
        for seed in args.seeds:
            for source in args.sources:
                results["runs"][source].append(train(source, family, settings, seed, out))
                results["summary"][source] = summary(results["runs"][source])
                (out / "results.json").write_text(json.dumps(results, indent=1))
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"{'source':12} {'mean':>9} {'CVaR0.5':>9} {'worst':>9} {'train s':>8}"
          f"   (means over {len(args.seeds)} seed(s))")
    for source, row in results["summary"].items():
        print(f"{source:12} {row['mean_return']:9.1f} {row['cvar_0.5']:9.1f} "
              f"{row['worst_cell']:9.1f} {row['train_seconds']:8.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
