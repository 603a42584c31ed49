"""Meta-test metrics: average and CVaR_α over tasks (paper Section 5, "Evaluation Metrics")."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.devices import CPU, forked_rng
from armeta_rl.learners.base import Leader
from armeta_rl.risk.tail import tail_size
from armeta_rl.tasks import TaskDistribution


def higher_is_better(metric: str) -> bool:
    """Whether larger values of ``metric`` are better (returns) or worse (errors)."""
    return metric == "return"


def cvar(values: Tensor, alpha: float, higher_better: bool = False) -> float:
    """CVaR_α, the meta-test metric of paper Sec. 5 ("Evaluation Metrics"): the mean of the worst
    ``(1 − α)`` fraction of ``values``, in float64.

    "Worst" is the largest values for a loss (``higher_better=False``) and the smallest for a
    return. The tail holds ``ceil((1 − α)·n)`` values (at least one; :func:`tail_size`). For a
    loss it is the number Σ_k ω_k L_k of Eq. (21) that the DR principle logs in training
    (:func:`~armeta_rl.risk.tail.tail_risk`), here summed in float64 for reports.
    """
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}")
    flat = values.detach().flatten().to(torch.float64)
    worst = flat.topk(tail_size(flat.numel(), alpha), largest=not higher_better).values
    return float(worst.mean())


def standard_error(values: Tensor) -> float | None:
    """Standard error of the mean over tasks, s/√n with s the sample standard deviation (``None``
    for a single task): how far the mean of ``n`` evaluation tasks may lie from the mean over the
    whole task distribution."""
    flat = values.detach().flatten().to(torch.float64)
    if flat.numel() < 2:
        return None
    return float(flat.std() / math.sqrt(flat.numel()))


def summarize(losses: Tensor, metric: str, alphas: Sequence[float]) -> dict[str, Any]:
    """``{"mean", "sem", "cvar": {α: …}, "n_tasks"}`` of per-task losses, in the units of
    ``metric`` (``sem``: the mean's standard error over tasks).

    For ``metric == "return"`` the per-task loss is the negative return, so the summary reports
    returns and CVaR over the lowest returns.
    """
    higher_better = higher_is_better(metric)
    values = -losses if higher_better else losses
    return {
        "mean": float(values.to(torch.float64).mean()),
        "sem": standard_error(values),
        "cvar": {str(alpha): cvar(values, alpha, higher_better) for alpha in alphas},
        "n_tasks": int(values.numel()),
    }


def evaluate_on(
    leader: Leader,
    distribution: TaskDistribution,
    collector: TaskCollector,
    n_tasks: int,
    alphas: Sequence[float],
    seed: int,
    device: torch.device = CPU,
) -> dict[str, Any]:
    """Score ``leader`` after adaptation on ``n_tasks`` tasks drawn from ``distribution``, all on
    ``device``: with ``distribution`` the trained adversary p_φ*, the mean is the estimate of
    E_{p_φ*}[L] of paper Eq. (48).

    Runs under its own seed inside a forked RNG (the CPU's and ``device``'s), so every method (and
    a resumed run) is scored on the same tasks and data, and training's random stream is left
    untouched.
    """
    with forked_rng(device):
        torch.manual_seed(seed)
        tasks = distribution.sample(n_tasks)
        with torch.no_grad():
            losses = leader.evaluate(leader.collect(tasks, collector))
    return summarize(losses, leader.metric, alphas)


def format_table(report: dict[str, Any]) -> str:
    """The ``eval.json`` figures as a fixed-width text table."""
    alphas = None
    rows = []
    for name, section in report.items():
        if not isinstance(section, dict) or "mean" not in section:
            continue
        alphas = alphas or list(section["cvar"])
        sem = section.get("sem")
        rows.append((name, section["mean"], "-" if sem is None else f"{sem:.4f}",
                     [section["cvar"][a] for a in alphas], section["n_tasks"]))
    header = f"{'distribution':<16}{'mean':>10}{'sem':>9}" + "".join(
        f"{'cvar_' + a:>11}" for a in alphas or []
    )
    lines = [f"metric: {report.get('metric')}", header + f"{'tasks':>8}"]
    for name, mean, sem, cvars, n in rows:
        lines.append(
            f"{name:<16}{mean:>10.4f}{sem:>9}" + "".join(f"{c:>11.4f}" for c in cvars)
            + f"{n:>8d}"
        )
    return "\n".join(lines)
