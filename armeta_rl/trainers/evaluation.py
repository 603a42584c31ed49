"""Meta-test metrics: average and CVaR_α over tasks (paper Section 5, "Evaluation Metrics")."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
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


class ReportInvalid(ValueError):
    """An evaluation report (``eval.json``, ``eval_vs_<name>.json``) that cannot be read or fails
    its schema (:func:`check_report`): the run or evaluation that wrote it is not finished."""


def check_report(report: Any, sections: tuple[str, ...] = ("initial",)) -> None:
    """Raise :class:`ReportInvalid` naming the first part of ``report`` (an ``eval.json``'s
    content) that no evaluation can have written.

    It must hold ``metric``, ``benchmark`` and ``method`` (strings) and the distributions
    ``sections``; every distribution's ``mean``, ``cvar`` (α in (0, 1) → value), ``sem`` and
    ``n_tasks`` must be what :func:`~armeta_rl.trainers.evaluation.summarize` makes of
    ``n_tasks`` finite values: finite numbers; each CVaR_α on the worse side of the mean and
    worsening as α grows; and ``sem`` at least the spread that the mean and the tails imply
    (:func:`spread_bound`). A hand-edited mean (``12345``) breaks those relations."""
    if not isinstance(report, dict):
        raise ReportInvalid("it is not a JSON object")
    for name in ("metric", "benchmark", "method"):
        if not isinstance(report.get(name), str):
            raise ReportInvalid(f"'{name}' is missing or not a string")
    for name in sections:
        if name not in report:
            raise ReportInvalid(f"it has no '{name}' distribution")
    higher = higher_is_better(report["metric"])
    for name, section in report.items():
        if isinstance(section, dict):
            _check_section(name, section, higher)


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(
        value)


def _check_section(name: str, section: dict[str, Any], higher: bool) -> None:
    mean, sem, cvar, n = (section.get(k) for k in ("mean", "sem", "cvar", "n_tasks"))
    if not _number(mean):
        raise ReportInvalid(f"'{name}.mean' = {mean!r} is not a finite number")
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ReportInvalid(f"'{name}.n_tasks' = {n!r} is not an integer >= 1")
    if (sem is None) != (n == 1) or (sem is not None and not (_number(sem) and sem >= 0)):
        raise ReportInvalid(f"'{name}.sem' = {sem!r} is not a standard error of {n} tasks")
    for key in ("entropy", "kl_p0"):
        if key in section and not _number(section[key]):
            raise ReportInvalid(f"'{name}.{key}' = {section[key]!r} is not a finite number")
    if not isinstance(cvar, dict) or not cvar:
        raise ReportInvalid(f"'{name}.cvar' is missing or empty")
    try:
        tails = sorted((float(alpha), value) for alpha, value in cvar.items())
    except (TypeError, ValueError):
        raise ReportInvalid(f"'{name}.cvar' has a key that is not a number") from None
    sign = -1.0 if higher else 1.0  # the tails are worse: larger losses, smaller returns
    worse = mean
    for alpha, value in tails:
        if not (0 < alpha < 1 and _number(value)):
            raise ReportInvalid(f"'{name}.cvar.{alpha}' = {value!r} is not a finite CVaR")
        if sign * (value - worse) < -_slack(value, worse):
            raise ReportInvalid(
                f"'{name}.cvar.{alpha}' = {value!r} is better than the mean or a smaller α's "
                f"CVaR ({worse!r})")
        if n > 1 and spread_bound(mean, value, n, tail_size(n, alpha)) > (
                sem**2 * n * (n - 1)) * (1 + 1e-6) + 1e-12 * (1 + mean**2):
            raise ReportInvalid(
                f"'{name}.sem' = {sem!r} is smaller than '{name}.mean' = {mean!r} and "
                f"'{name}.cvar.{alpha}' = {value!r} allow")
        worse = value


def _slack(a: float, b: float) -> float:
    return 1e-9 * (1.0 + abs(a) + abs(b))


def spread_bound(mean: float, tail_mean: float, n: int, k: int) -> float:
    """The least sum of squared deviations from ``mean`` that ``n`` values can have when ``k``
    of them average ``tail_mean``: the between-group sum of squares
    ``k (C − m)² + (n − k) (R − m)²``, ``R`` the other values' mean. ``sem² · n · (n − 1)`` is
    their whole sum of squares, so it is at least this."""
    if k >= n:
        return 0.0
    rest = (n * mean - k * tail_mean) / (n - k)
    return k * (tail_mean - mean) ** 2 + (n - k) * (rest - mean) ** 2


def read_report(path: Path, sections: tuple[str, ...] = ("initial",)) -> dict[str, Any]:
    """The evaluation report at ``path`` if it passes :func:`check_report`.

    Raises:
        ReportInvalid: ``path`` is missing, unreadable, not UTF-8 JSON, or fails the schema.
    """
    try:
        report = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ReportInvalid("it does not exist") from None
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise ReportInvalid(f"it cannot be read: {' '.join(str(error).split())}") from None
    check_report(report, sections)
    return report
