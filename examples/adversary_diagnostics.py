"""Why does my adversary not move? The loss landscape and the adversary's gradient at p0.

For a finished training run of a regression or system-identification benchmark with a 2-D task
box (sinusoid, pendulum, acrobot), this scores the run's learner and reports what decides whether
the flow adversary leaves p0 (docs/protocol.md, section 6, which reads these numbers for
Pendulum-N):

(a) the landscape: E[L | τ], the learner's adapted loss of task τ, on a grid over the box (the
    axes' end points included, ``--episodes`` episodes per point), weighed by p0 (and by the
    ``--compare`` distribution): its mean, the sd of E[L | τ] over the distribution (the signal an
    adversary can find) against the sd of L between one task's episodes (the noise), and the
    density on the grid that maximizes the follower's objective J = E_p[L] + λ·E_p0[ln p] (paper
    Eq. (6)), with its E[L] and KL(p0 ‖ p);
(b) the adversary's gradient at φ0 (paper Eq. (17), the package's own surrogate), over
    ``--batches`` batches of ``--tasks`` tasks drawn from p_φ0 = p0: the norm of its mean against
    the sd of one batch's estimate, and the median norm of one batch's gradient against the run's
    clipping norm;
(c) with ``--minmax``, the authors' code's adversarial evaluation at an unmoved flow: grids of
    ``--minmax-draws`` draws per identifier of its p0, mapped onto the box by the batch's min–max
    (the smallest value of each identifier goes to the box's low edge, the largest to its high
    edge), scored with the same episodes as the unmapped grids.

λ is the run's ``risk.ar.lam`` (``ArOptions``' default where the config has none); p0, the box
and the flow of φ0 come from the run's config. Everything is seeded by ``--seed`` and
deterministic on the CPU.

    python examples/adversary_diagnostics.py runs/maml_n --compare uniform --minmax
    python examples/adversary_diagnostics.py runs/maml_n --grid 7 --episodes 4 --json diag.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, NoReturn

import torch
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.adversary.objective import adversary_surrogate, surrogate_gradient
from armeta_rl.collectors.base import TaskCollector
from armeta_rl.collectors.regression import SinusoidCollector
from armeta_rl.collectors.sysid import SysIdCollector
from armeta_rl.config import load_run_config
from armeta_rl.errors import ConfigError
from armeta_rl.learners.base import Leader
from armeta_rl.risk.adversarial import ArOptions
from armeta_rl.tasks.distributions import BoxUniform, TaskDistribution, TruncatedNormal
from armeta_rl.trainers.evaluation import cvar
from armeta_rl.trainers.players import load_players

CHUNK = 400
"""Tasks scored in one call of the learner: bounds the memory of a grid's episodes."""
COMPARE = ("none", "uniform")
COLLECTORS = (SinusoidCollector, SysIdCollector)


class UsageError(ValueError):
    """A command-line argument argparse refused (reported as one line, exit code 2)."""


class Parser(argparse.ArgumentParser):
    """An argument parser whose refusals reach :func:`main` as :class:`UsageError`."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(message)


def check_run(cfg: DictConfig, key: str) -> None:
    """Refuse a run whose benchmark these diagnostics do not cover: the task box must be 2-D and
    the tasks scored by a regression or system-identification collector."""
    names = list(cfg.benchmark.space.names)
    if len(names) != 2:
        raise ConfigError(key, cfg.benchmark.name, f"its task space {names} is {len(names)}-D: "
                          "the diagnostics need a 2-D task box (sinusoid, pendulum, acrobot)")
    target = OmegaConf.select(cfg, "benchmark.eval_collector._target_")
    if target is None or not issubclass(get_class(target), COLLECTORS):
        raise ConfigError(key, cfg.benchmark.name, "the diagnostics need a regression or "
                          f"system-identification benchmark, not one collected by {target}")


def task_losses(leader: Leader, collector: TaskCollector, initial: TaskDistribution,
                params: Tensor, seed: int) -> Tensor:
    """The learner's adapted loss ``[n]`` (float64) of each task ``params [n, d]``, its data drawn
    after ``torch.manual_seed(seed)``, in batches of :data:`CHUNK` tasks."""
    torch.manual_seed(seed)
    tasks = initial.as_tasks(params, torch.zeros(len(params), dtype=torch.float64))
    with torch.no_grad():
        return torch.cat([leader.evaluate(leader.collect(chunk, collector)).double()
                          for chunk in tasks.split(CHUNK)])


def box_grid(distribution: TaskDistribution, points: int) -> Tensor:
    """``points``² identifiers ``[points², 2]`` on a grid of the box, its edges included (the
    first identifier varies slowest)."""
    axes = [torch.linspace(lo, hi, points, dtype=torch.float64)
            for lo, hi in zip(distribution.low.tolist(), distribution.high.tolist())]
    return torch.cartesian_prod(*axes)


def grid_weights(distribution: TaskDistribution, grid: Tensor) -> Tensor:
    """The distribution's density at the grid points, normalized to sum to 1."""
    density = distribution.log_prob(grid).exp()
    return density / density.sum()


def landscape(means: Tensor, variances: Tensor, weights: Tensor) -> dict[str, float]:
    """The weighted mean of E[L | τ] over the grid, its sd over the grid (the signal) and the
    root of the weighted mean of the variance of L within a task (the episodes' noise)."""
    mean = (weights * means).sum()
    return {"mean": float(mean),
            "sd_signal": float((weights * (means - mean) ** 2).sum().sqrt()),
            "sd_noise": float((weights * variances).sum().sqrt())}


def objective_maximizer(means: Tensor, weights: Tensor, lam: float) -> dict[str, Any]:
    """The density p on the grid that maximizes the follower's objective J = Σ p·E[L | τ] +
    λ·Σ p0·ln p (paper Eq. (6), with p0's grid ``weights``): p = λ·p0 / (c − E[L | τ]), c > max
    E[L | τ] fixed by Σ p = 1 (found by bisection). At λ = 0 it is the point mass on the worst
    grid point, at KL(p0 ‖ p) = ∞."""
    if lam == 0:
        density = torch.zeros_like(means)
        density[means.argmax()] = 1.0
        kl = math.inf
    else:
        lo, hi = float(means.max()), float(means.max()) + lam   # Σ p ≤ 1 at c = max + λ
        for _ in range(200):
            c = (lo + hi) / 2
            if c in (lo, hi):
                break
            lo, hi = (c, hi) if (weights * lam / (c - means)).sum() > 1 else (lo, c)
        density = weights * lam / (hi - means)
        density = density / density.sum()
        support = weights > 0
        kl = float((weights[support] * (weights[support] / density[support]).log()).sum())
    return {"density": density.tolist(), "loss_mean": float((density * means).sum()), "kl": kl}


def adversary_gradient(options: ArOptions, leader: Leader, collector: TaskCollector,
                       initial: TaskDistribution, lam: float, batches: int, tasks: int,
                       seed: int) -> dict[str, float]:
    """The score-function estimate of ∇_φ J at φ0 (paper Eq. (17), :func:`adversary_surrogate`
    with the run's baseline and p0 sample size) from ``batches`` batches of ``tasks`` tasks of
    p_φ0 = p0 (the run's flow, its parameters drawn after ``torch.manual_seed(seed)``): the norm
    of the mean gradient (debiased: |mean|² less the noise's share), the sd of one batch's
    estimate (the root of the mean squared distance to the mean) and the median per-batch
    norm, against the run's clipping norm ``risk.ar.grad_clip``."""
    torch.manual_seed(seed)
    adversary = FlowAdversary(initial.space, initial, options.flow, **options.flow_kwargs)
    phi = list(adversary.parameters())
    drawn = adversary.sample(batches * tasks)
    losses = task_losses(leader, collector, initial, drawn["params"].double(), seed + 1)
    optimizer = torch.optim.SGD(phi, lr=0.0)   # only holds φ for surrogate_gradient
    gradients, norms = [], []
    for batch in range(batches):
        part = slice(batch * tasks, (batch + 1) * tasks)
        surrogate, _ = adversary_surrogate(adversary, drawn[part], losses[part], lam,
                                           initial.sample_params(options.initial_samples),
                                           options.baseline)
        norms.append(float(surrogate_gradient(surrogate, optimizer, phi, None)))
        gradients.append(torch.cat([p.grad.flatten() for p in phi if p.grad is not None]))
    g = torch.stack(gradients).double()
    noise = ((g - g.mean(0)) ** 2).sum(1).mean()
    return {
        "mean_norm": float((g.mean(0).pow(2).sum() - noise / batches).clamp(min=0).sqrt()),
        "batch_sd": float(noise.sqrt()),
        "median_batch_norm": float(torch.tensor(norms).median()),
        "grad_clip": options.grad_clip,
    }


def code_initial_draws(initial: TaskDistribution, n: int, generator: torch.Generator) -> Tensor:
    """``n`` draws ``[n, d]`` per identifier of p0 as the authors' code makes them: a normal p0
    as ``np.clip(np.random.normal(loc, scale), low, high)`` (clipped, not truncated), a uniform
    one uniformly on the box."""
    d = initial.space.dim
    if isinstance(initial, TruncatedNormal):
        z = torch.randn(n, d, generator=generator, dtype=torch.float64)
        return (initial.loc + initial.scale * z).clamp(initial.low, initial.high)
    unit = torch.rand(n, d, generator=generator, dtype=torch.float64)
    return initial.low + (initial.high - initial.low) * unit


def minmax_stretch(values: Tensor, low: Tensor, high: Tensor) -> Tensor:
    """The authors' code's map of a batch onto the box (``Distribution_Adversary.forward``): per
    identifier, the batch's smallest value goes to ``low``, its largest to ``high``."""
    smallest, largest = values.min(0).values, values.max(0).values
    return low + (high - low) * (values - smallest) / (largest - smallest)


def minmax_gap(leader: Leader, collector: TaskCollector, initial: TaskDistribution, sets: int,
               draws: int, seed: int) -> dict[str, float]:
    """The learner on ``sets`` grids of ``draws`` code-style p0 draws per identifier
    (``draws``² tasks each) and on their min–max stretched copies, each pair scored on the same
    episodes: mean and CVaR0.5 (per set, averaged), and the difference of the means with its
    standard error over the sets."""
    generator = torch.Generator().manual_seed(seed)
    plain, stretched = [], []
    for index in range(sets):
        values = code_initial_draws(initial, draws, generator)
        for out, v in ((plain, values), (stretched, minmax_stretch(values, initial.low,
                                                                   initial.high))):
            out.append(task_losses(leader, collector, initial, torch.cartesian_prod(*v.T),
                                   seed + 1000 + index))
    plain, stretched = torch.stack(plain), torch.stack(stretched)
    difference = stretched.mean(1) - plain.mean(1)
    return {
        "sets": sets, "tasks_per_set": draws ** 2,
        "plain_mean": float(plain.mean()),
        "plain_cvar_0.5": sum(cvar(row, 0.5) for row in plain) / sets,
        "stretched_mean": float(stretched.mean()),
        "stretched_cvar_0.5": sum(cvar(row, 0.5) for row in stretched) / sets,
        "difference": float(difference.mean()),
        "difference_se": float(difference.std() / sets ** 0.5),
    }


def diagnose(run: str, args: argparse.Namespace) -> dict[str, Any]:
    """All the diagnostics of ``run`` as one JSON-ready dict."""
    check_run(load_run_config(run, "run"), "run")
    cfg, players = load_players(run, "run", device="cpu")
    options: ArOptions = cfg.risk["ar"]
    lam = float(options.lam)
    leader, collector, initial = players.leader, players.eval_collector, players.initial
    grid = box_grid(initial, args.grid)
    losses = task_losses(leader, collector, initial, grid.repeat_interleave(args.episodes, 0),
                         args.seed).reshape(len(grid), args.episodes)
    means, variances = losses.mean(1), losses.var(1)
    distributions = {f"p0 ({cfg.benchmark.initial.kind})": initial}
    if args.compare == "uniform":
        distributions["uniform"] = BoxUniform(players.space)
    weighed = {}
    for name, distribution in distributions.items():
        weights = grid_weights(distribution, grid)
        weighed[name] = {"weights": weights.tolist(), **landscape(means, variances, weights),
                         "maximizer": objective_maximizer(means, weights, lam)}
    names = list(players.space.names)
    report = {
        "run": run, "benchmark": cfg.benchmark.name, "method": cfg.method.name,
        "seed": args.seed, "lam": lam,
        "grid": {"names": names, "points_per_axis": args.grid, "episodes": args.episodes,
                 "params": grid.tolist(), "loss_mean": means.tolist(),
                 "loss_sd": variances.sqrt().tolist()},
        "distributions": weighed,
        "gradient": {"batches": args.batches, "tasks": args.tasks,
                     **adversary_gradient(options, leader, collector, initial, lam, args.batches,
                                          args.tasks, args.seed)},
    }
    if args.minmax:
        report["minmax"] = minmax_gap(leader, collector, initial, args.minmax_sets,
                                      args.minmax_draws, args.seed)
    return report


def table(report: dict[str, Any]) -> str:
    """The report as readable text."""
    grid = report["grid"]
    g, names = grid["points_per_axis"], grid["names"]
    means = torch.tensor(grid["loss_mean"]).reshape(g, g)
    params = torch.tensor(grid["params"]).reshape(g, g, 2)
    lines = [f"run {report['run']}: {report['benchmark']}, {report['method']}, "
             f"λ = {report['lam']:g}, seed {report['seed']}",
             f"E[L | τ] on a {g} × {g} grid of the box ({grid['episodes']} episodes per point)"]
    for axis, values in ((1, params[0, :, 1]), (0, params[:, 0, 0])):
        other = 1 - axis
        marginal = means.mean(other)
        lines.append(f"  averaged over {names[other]}, against {names[axis]}: " + "  ".join(
            f"{v:.2f}: {m:.3f}" for v, m in zip(values.tolist(), marginal.tolist())))
    lines.append(f"{'distribution':16} {'E[L]':>8} {'sd E[L|τ]':>10} {'sd in task':>11} "
                 f"{'argmax J: E[L]':>15} {'KL(p0‖p)':>9}")
    for name, row in report["distributions"].items():
        best = row["maximizer"]
        lines.append(f"{name:16} {row['mean']:8.4f} {row['sd_signal']:10.4f} "
                     f"{row['sd_noise']:11.4f} {best['loss_mean']:15.4f} {best['kl']:9.4f}")
    grad = report["gradient"]
    clip = "none" if grad["grad_clip"] is None else f"{grad['grad_clip']:g}"
    lines.append(f"adversary's gradient at φ0 (Eq. (17)), {grad['batches']} batches of "
                 f"{grad['tasks']} tasks: |E g| {grad['mean_norm']:.4f}, sd of one batch's g "
                 f"{grad['batch_sd']:.4f}, median |g| {grad['median_batch_norm']:.4f} "
                 f"(clip {clip})")
    if "minmax" in report:
        mm = report["minmax"]
        lines.append(
            f"code-style p0 grids ({mm['sets']} sets of {mm['tasks_per_set']} tasks): mean "
            f"{mm['plain_mean']:.4f} (CVaR0.5 {mm['plain_cvar_0.5']:.4f}); min–max stretched "
            f"{mm['stretched_mean']:.4f} (CVaR0.5 {mm['stretched_cvar_0.5']:.4f}); difference "
            f"{mm['difference']:.4f} ± {mm['difference_se']:.4f} (s.e.)")
    return "\n".join(lines)


def at_least(name: str, value: int, smallest: int) -> None:
    """Refuse an integer option below ``smallest``."""
    if value < smallest:
        raise ConfigError(name, value, f"must be an integer >= {smallest}")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a finished training run directory (with a checkpoint)")
    parser.add_argument("--grid", type=int, default=13, help="grid points per axis")
    parser.add_argument("--episodes", type=int, default=16, help="episodes per grid point")
    parser.add_argument("--compare", default="none", choices=COMPARE,
                        help="a distribution to weigh the grid by besides p0")
    parser.add_argument("--batches", type=int, default=200, help="batches of the gradient")
    parser.add_argument("--tasks", type=int, default=16, help="tasks per gradient batch")
    parser.add_argument("--minmax", action="store_true",
                        help="also score the authors' code's min–max stretched p0 grids")
    parser.add_argument("--minmax-sets", type=int, default=10, help="grids of the min–max test")
    parser.add_argument("--minmax-draws", type=int, default=10,
                        help="draws per identifier of one min–max grid")
    parser.add_argument("--seed", type=int, default=0, help="seeds every random draw")
    parser.add_argument("--json", default=None, help="also write the numbers to this file")
    args = parser.parse_args(argv)
    for name, smallest in (("grid", 2), ("episodes", 2), ("batches", 2), ("tasks", 2),
                           ("minmax_sets", 2), ("minmax_draws", 2)):
        at_least("--" + name.replace("_", "-"), getattr(args, name), smallest)
    return args


def main(argv: list[str] | None = None) -> int:
    """Print the diagnostics (and write them to ``--json``); exit code 2 with one line on a bad
    option or a run the diagnostics do not cover."""
    try:
        args = parse_args(argv)
        report = diagnose(args.run, args)
        if args.json is not None:
            Path(args.json).write_text(json.dumps(report, indent=1))
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(table(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
