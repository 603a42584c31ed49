"""Meta-test metrics: average and CVaR_α over tasks (paper Section 5, "Evaluation Metrics"), each
with its standard error over tasks, every task scored on R independent rollouts, and paired
differences between two learners scored on the same tasks and random streams (docs/meta-rl.md)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.devices import CPU, forked_rng
from armeta_rl.errors import ConfigError
from armeta_rl.learners.base import Leader
from armeta_rl.risk.tail import tail_size
from armeta_rl.run_files import FileRefused, read_text
from armeta_rl.tasks import TaskDistribution
from armeta_rl.tasks.protocol import TASK_KEY, per_rollout, repeat_tasks

REPORT_BYTES = 64 * 2**20
"""The most an evaluation report is read (its per-task scores of 500 tasks × every section
take well under a MiB): a link to ``/dev/zero`` or a huge file is refused, not read into
memory."""
PER_TASK_DIGITS = 6
"""Significant digits of the per-task scores an evaluation report keeps (for paired
differences between reports)."""


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

    Examples:
        >>> import torch
        >>> from armeta_rl.trainers import cvar
        >>> losses = torch.tensor([1.0, 2.0, 3.0, 4.0])
        >>> cvar(losses, alpha=0.5)  # the mean of the worst half
        3.5
        >>> cvar(losses, alpha=0.5, higher_better=True)  # as returns: the lowest half
        1.5
    """
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}")
    flat = values.detach().flatten().to(torch.float64)
    worst = flat.topk(tail_size(flat.numel(), alpha), largest=not higher_better).values
    return float(worst.mean())


def cvar_influence(values: Tensor, alpha: float, higher_better: bool = False) -> Tensor:
    """The influence values ``z`` ``[n]`` (float64) of the CVaR_α estimate of :func:`cvar`:
    z_i = t + (x_i − t)₊·n/k for losses and z_i = t − (t − x_i)₊·n/k for returns, with k the tail
    size (:func:`tail_size`) and t the worst value outside the tail (the (k+1)-th worst; for
    k = n, z = x).

    CVaR = t + E[(L − t)₊]/(1 − α) for a threshold t at the α-quantile (Rockafellar and Uryasev
    2000), so mean(z) is exactly :func:`cvar` (the tail's values are at least t, the others at
    most t) and std(z)/√n is the estimate's standard error by the delta method; differences of
    two learners' z on the same tasks give the paired standard error of a CVaR difference.
    Taking t just outside the tail rather than at its last value keeps the tail's own spread in
    z when the tail is a few values (one value: the error is that value's distance to the
    next).
    """
    flat = values.detach().flatten().to(torch.float64)
    n, size = flat.numel(), tail_size(flat.numel(), alpha)
    if size == n:
        return flat
    worst_first = -flat if higher_better else flat
    threshold = worst_first.topk(size + 1).values[-1]
    z = threshold + (worst_first - threshold).clamp(min=0) * (n / size)
    return -z if higher_better else z


def standard_error(values: Tensor) -> float | None:
    """Standard error of the mean over tasks, s/√n with s the sample standard deviation (``None``
    for a single task): how far the mean of ``n`` evaluation tasks may lie from the mean over the
    whole task distribution."""
    flat = values.detach().flatten().to(torch.float64)
    if flat.numel() < 2:
        return None
    return float(flat.std() / math.sqrt(flat.numel()))


def rollout_sd(per_rollout_values: Tensor) -> float | None:
    """The standard deviation of one rollout's score around its task's mean, pooled over tasks
    (√ of the mean within-task sample variance) from values ``[R, n]``; ``None`` for R = 1. A
    task's score, the mean of R rollouts, has noise rollout_sd/√R."""
    if per_rollout_values.shape[0] < 2:
        return None
    return float(per_rollout_values.to(torch.float64).var(0).mean().sqrt())


def summarize(losses: Tensor, metric: str, alphas: Sequence[float]) -> dict[str, Any]:
    """``{"mean", "sem", "cvar": {α: …}, "cvar_sem": {α: …}, "n_tasks", "rollouts",
    "rollout_sd", "per_task"}`` of per-task losses ``[n]`` or, with R rollouts per task,
    ``[R, n]``, in the units of ``metric``.

    A task's score is the mean of its R rollouts; ``sem`` and ``cvar_sem`` are the standard
    errors over tasks of the mean and of CVaR_α (:func:`standard_error`,
    :func:`cvar_influence`); ``rollout_sd`` is one rollout's noise (:func:`rollout_sd`);
    ``per_task`` holds the task scores (:data:`PER_TASK_DIGITS` significant digits) for paired
    differences (:func:`paired_difference`). For ``metric == "return"`` the per-task loss is the
    negative return, so the summary reports returns and CVaR over the lowest returns.

    Examples:
        >>> import torch
        >>> from armeta_rl.trainers import summarize
        >>> report = summarize(torch.tensor([1.0, 2.0, 3.0, 4.0]), "mse", alphas=[0.5])
        >>> report["mean"], report["cvar"], report["n_tasks"]
        (2.5, {'0.5': 3.5}, 4)
    """
    higher_better = higher_is_better(metric)
    rollouts = losses.detach().to(torch.float64).reshape(-1, losses.shape[-1])
    values = -rollouts if higher_better else rollouts
    scores = values.mean(0)
    return {
        "mean": float(scores.mean()),
        "sem": standard_error(scores),
        "cvar": {str(alpha): cvar(scores, alpha, higher_better) for alpha in alphas},
        "cvar_sem": {str(alpha): standard_error(cvar_influence(scores, alpha, higher_better))
                     for alpha in alphas},
        "n_tasks": int(scores.numel()),
        "rollouts": int(values.shape[0]),
        "rollout_sd": rollout_sd(values),
        "per_task": [float(f"{v:.{PER_TASK_DIGITS}g}") for v in scores.tolist()],
    }


def adaptation_gain(before: Tensor, after: Tensor, metric: str) -> dict[str, Any]:
    """The score before adaptation and the adaptation gain, paired task by task, from per-task
    losses before and after adaptation on the same data, ``[n]`` or with R rollouts per task
    ``[R, n]`` (a task's score is the mean of its rollouts):
    ``{"before", "before_sem", "gain", "gain_sem", "improved"}``.

    ``before`` is in the units of ``metric`` (a return for ``"return"``); the gain is the
    improvement the inner step makes, after − before for returns and before − after for
    errors, so it is positive when adaptation helps; ``gain_sem`` is its standard error over
    tasks (what the tasks share cancels in the per-task difference) and ``improved`` counts the
    tasks it improved. A learner whose gain on p0 is not beyond twice ``gain_sem`` does not
    adapt (:func:`adapts`).
    """
    pre = before.detach().to(torch.float64).reshape(-1, before.shape[-1]).mean(0)
    post = after.detach().to(torch.float64).reshape(-1, after.shape[-1]).mean(0)
    sign = -1.0 if higher_is_better(metric) else 1.0
    gains = pre - post  # in losses: lower after adaptation is a gain
    return {
        "before": float(sign * pre.mean()),
        "before_sem": standard_error(pre),
        "gain": float(gains.mean()),
        "gain_sem": standard_error(gains),
        "improved": int((gains > 0).sum()),
    }


def adapts(gain: float, gain_sem: float | None) -> bool:
    """Whether an adaptation gain is beyond twice its standard error over tasks: the learner's
    inner step measurably improves it (docs/meta-rl.md, "Does the learner adapt")."""
    return gain_sem is not None and gain > 2.0 * gain_sem


GAP_SHARE_MAX_SEM = 1.0
"""The largest standard error over tasks a share of the goal-blind gap closed may have and be
reported (:func:`share_resolved`): 1, the whole distance from ignoring the goal (0) to knowing
it (1)."""


def share_resolved(sem: float | None) -> bool:
    """Whether a share of the goal-blind gap closed (:func:`gap_closed`) with standard error
    ``sem`` over tasks means anything: its error is known (two tasks or more) and at most
    :data:`GAP_SHARE_MAX_SEM`. The delta method's error is SE(r)/gap, r_i = (a_i − b_i) −
    share·(o_i − b_i), so the rule holds exactly where the gap R̄_oracle − R̄_blind is at least
    one standard error of the per-task residual it divides: where the gap stands out of the
    noise of the returns it scales. On a distribution concentrated on one goal (an
    adversary's p_φ) the best goal-blind policy is the oracle, the gap all but vanishes and the
    share runs to −10⁵ %; a rule on the gap's own standard error need not catch this (the
    references are exact, so a tiny gap can be a precise one), and one on a fraction of
    |R̄_blind| cannot (R_oracle = 0 for the velocity families and Ant-Pos: the gap is |R̄_blind|)."""
    return sem is not None and sem <= GAP_SHARE_MAX_SEM


def gap_closed(achieved: Tensor, blind: Tensor, oracle: Tensor) -> tuple[float | None,
                                                                        float | None]:
    """The share of the goal-blind gap the adapted policy closes on a batch of tasks, and its
    standard error over tasks: (R̄_adapted − R̄_blind) / (R̄_oracle − R̄_blind) from the per-task
    goal terms ``[n]`` of the adapted policy, of the best goal-blind policy for the batch and of
    the best policy with the goal known (a collector's ``goal_references``).

    0 is a policy no better than one that ignores the goal, 1 one as good as knowing it: how much
    of what the goal is worth one inner step recovers. A ratio of means (not a mean of per-task
    ratios, which a task whose goal the blind policy meets would blow up); its standard error is
    the delta method's, std(z)/√n with z_i = ((a_i − b_i) − share·(o_i − b_i)) / mean(o − b).
    ``(None, None)`` where there is no gap (the blind policy as good as the oracle on average)
    or the gap is too small against the evaluation's noise for the share to mean anything: its
    standard error over tasks above 1 (100 points), or unknown with one task
    (:func:`share_resolved`)."""
    adapted, blind, oracle = (v.detach().to(torch.float64).flatten()
                              for v in (achieved, blind, oracle))
    gap = (oracle - blind).mean()
    if not gap > 0:
        return None, None
    share = (adapted - blind).mean() / gap
    sem = standard_error(((adapted - blind) - share * (oracle - blind)) / gap)
    if not share_resolved(sem):
        return None, None
    return float(share), sem


def goal_section(achieved: Tensor, blind: Tensor, oracle: Tensor) -> dict[str, Any]:
    """A report's ``goal``: the mean goal terms over tasks (``achieved``, ``blind``,
    ``oracle``) and the share of the goal-blind gap closed with its standard error
    (:func:`gap_closed`), from per-task values ``[n]`` or, with R rollouts per task,
    ``[R, n]`` (a task's value is the mean of its rollouts)."""
    per_task = [v.detach().to(torch.float64).reshape(-1, v.shape[-1]).mean(0)
                for v in (achieved, blind, oracle)]
    share, sem = gap_closed(*per_task)
    return {"achieved": float(per_task[0].mean()), "blind": float(per_task[1].mean()),
            "oracle": float(per_task[2].mean()), "gap_closed": share, "gap_closed_sem": sem}


def quarter_scores(scores: Tensor, quarters: Tensor) -> list[float | None]:
    """The mean score ``[4]`` of the tasks in each quarter of the box (their
    :meth:`~armeta_rl.tasks.TaskSpace.quarter` ``[n]``), ``None`` for a quarter without
    tasks: where on the box the learner does worst, which an adversary's
    ``quarter_mass`` is read against."""
    values = scores.detach().to(torch.float64).flatten()
    return [float(values[quarters == q].mean()) if bool((quarters == q).any()) else None
            for q in range(4)]


def paired_difference(first: Sequence[float], second: Sequence[float], metric: str,
                      alphas: Sequence[float]) -> dict[str, Any]:
    """First learner minus second on the same tasks (their reports' ``per_task`` scores, in
    task order): ``{"mean", "sem", "cvar": {α: …}, "cvar_sem": {α: …}, "n_tasks"}``. The
    standard errors are over tasks of the per-task differences (of the mean; of the CVaR
    influence values, :func:`cvar_influence`), so what the two learners share (the tasks, the
    random streams) cancels."""
    a, b = torch.tensor(first, dtype=torch.float64), torch.tensor(second, dtype=torch.float64)
    if a.shape != b.shape:
        raise ValueError(f"paired scores need the same tasks: {a.numel()} against {b.numel()}")
    higher_better = higher_is_better(metric)
    return {
        "mean": float((a - b).mean()),
        "sem": standard_error(a - b),
        "cvar": {str(alpha): cvar(a, alpha, higher_better) - cvar(b, alpha, higher_better)
                 for alpha in alphas},
        "cvar_sem": {str(alpha): standard_error(cvar_influence(a, alpha, higher_better)
                                                - cvar_influence(b, alpha, higher_better))
                     for alpha in alphas},
        "n_tasks": int(a.numel()),
    }


CURVE_BEYOND = 2
"""How many inner steps past the trained number an adaptation curve goes by default."""


def curve_steps(leader: Leader, adaptation_steps: int | None) -> int | None:
    """The k of ``leader``'s adaptation curve (``eval.adaptation_steps``; ``None``: the inner
    steps it trains with and :data:`CURVE_BEYOND` more), or ``None`` for a leader without one
    (regression, system identification). A k set for such a leader is refused."""
    if not callable(getattr(leader, "adaptation_curve", None)):
        if adaptation_steps is not None:
            raise ConfigError("eval.adaptation_steps", adaptation_steps,
                              "only a meta-RL learner (MAML-TRPO, MAML-PPO) reports an "
                              "adaptation curve: leave it null")
        return None
    return adaptation_steps if adaptation_steps is not None else (
        leader.inner_steps + CURVE_BEYOND)


def curve_summary(losses: Tensor, rollouts: int, metric: str) -> dict[str, Any]:
    """``{"inner_steps", "mean", "sem"}`` of per-task losses after 0..k inner steps
    ``[k + 1, R·n]`` (rollout-major, :func:`~armeta_rl.tasks.protocol.repeat_tasks`): at each
    step the mean over tasks of their scores (a task's: the mean of its R rollouts) and its
    standard error, in the units of ``metric``."""
    sign = -1.0 if higher_is_better(metric) else 1.0
    scores = [sign * per_rollout(step.detach().to(torch.float64), rollouts).mean(0)
              for step in losses]
    return {"inner_steps": list(range(len(scores))),
            "mean": [float(values.mean()) for values in scores],
            "sem": [standard_error(values) for values in scores]}


def evaluate_on(
    leader: Leader,
    distribution: TaskDistribution,
    collector: TaskCollector,
    n_tasks: int,
    alphas: Sequence[float],
    seed: int,
    device: torch.device = CPU,
    rollouts: int = 1,
    adaptation_steps: int | None = None,
) -> dict[str, Any]:
    """Score ``leader`` after adaptation on ``n_tasks`` tasks drawn from ``distribution``, each
    task on ``rollouts`` independent rollouts (R: adaptation from fresh data, then the adapted
    learner's loss), all on ``device``: with ``distribution`` the trained adversary p_φ*, the mean
    is the estimate of E_{p_φ*}[L] of paper Eq. (48). Where the leader reports its loss before
    adaptation (meta-RL), the report's ``"adaptation"`` holds the score before adaptation and the
    paired gain on the same data (:func:`adaptation_gain`); where the collector knows the
    goal-blind and the oracle references of its tasks (``goal_references``), ``"goal"`` holds
    the share of the goal-blind gap the adapted policy closes (:func:`goal_section`).
    ``"quarter_scores"`` is the mean score of the tasks in each quarter of the box
    (:func:`quarter_scores`). Where the leader takes inner steps on episodes (meta-RL),
    ``"adaptation_curve"`` holds its score after 0, 1, ..., k inner steps (:func:`curve_steps`,
    :func:`curve_summary`), the first two from the same data.

    The R copies of every task are collected and adapted in one batch (rollout-major,
    :func:`~armeta_rl.tasks.protocol.repeat_tasks`). Runs under its own seed inside a forked RNG
    (the CPU's and ``device``'s), so every method (and a resumed run) is scored on the same tasks
    and random streams, and training's random stream is left untouched.

    Examples:
        >>> from armeta_rl.collectors import SinusoidCollector
        >>> from armeta_rl.learners import MAMLLeader, make_mlp
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> from armeta_rl.trainers import evaluate_on
        >>> space = TaskSpace(["amplitude", "phase"], low=[0.1, 0.0], high=[5.0, 3.1416])
        >>> net = make_mlp(1, 1, hidden=[16])
        >>> for weight, bias in net.layers():  # a network predicting 0: its MSE is about a²/2
        ...     _ = weight.data.zero_(), bias.data.zero_()
        >>> leader = MAMLLeader(net, SinusoidCollector())
        >>> collector = SinusoidCollector(n_query=100)  # the evaluation's collector
        >>> report = evaluate_on(leader, BoxUniform(space), collector, n_tasks=200, alphas=[0.9],
        ...                      seed=0)
        >>> # E[a²/2] over a ~ U[0.1, 5] is (5³ - 0.1³) / (6 · 4.9) = 4.25
        >>> round(report["mean"], 2), round(report["sem"], 2)
        (4.1, 0.26)
        >>> round(report["cvar"]["0.9"], 2)  # the worst tenth: amplitudes near 5, a²/2 near 12
        11.7
        >>> [round(score, 2) for score in report["quarter_scores"]]  # low amplitudes, then high
        [1.16, 1.21, 7.09, 7.28]
    """
    steps = curve_steps(leader, adaptation_steps)
    with forked_rng(device):
        torch.manual_seed(seed)
        tasks = distribution.sample(n_tasks)
        repeated = repeat_tasks(tasks, rollouts)
        with torch.no_grad():
            data = leader.collect(repeated, collector)
            losses, before = leader.evaluate(data), leader.evaluate_before(data)
            references = goal_references(collector, repeated[TASK_KEY],
                                         leader.adapted_episodes(data))
        curve = None if steps is None else leader.adaptation_curve(data, steps, collector)
    report = summarize(per_rollout(losses, rollouts), leader.metric, alphas)
    if before is not None:
        report["adaptation"] = adaptation_gain(per_rollout(before, rollouts),
                                               per_rollout(losses, rollouts), leader.metric)
    if references is not None:
        report["goal"] = goal_section(*(per_rollout(references[key], rollouts)
                                        for key in ("achieved", "blind", "oracle")))
    sign = -1.0 if higher_is_better(leader.metric) else 1.0
    scores = sign * per_rollout(losses, rollouts).to(torch.float64).mean(0)
    report["quarter_scores"] = quarter_scores(
        scores, distribution.space.quarter(tasks[TASK_KEY]).to(scores.device))
    if curve is not None:
        report["adaptation_curve"] = curve_summary(curve, rollouts, leader.metric)
    return report


def goal_references(collector: TaskCollector, params: Tensor,
                    episodes: TensorDictBase | None) -> dict[str, Tensor] | None:
    """The collector's goal references of the tasks ``params`` ``[K, d]`` and their adapted
    episodes (``goal_references(params, episodes)``: per task the goal term achieved, the best
    goal-blind policy's and the oracle's), or ``None`` for a leader without episodes or a
    collector that knows none."""
    known = getattr(collector, "goal_references", None)
    if episodes is None or known is None:
        return None
    return known(params, episodes)


def format_table(report: dict[str, Any]) -> str:
    """The ``eval.json`` figures as a fixed-width text table: each mean and CVaR with its
    standard error over tasks, the tasks and the rollouts per task."""
    alphas = None
    lines = []
    for name, section in report.items():
        if not isinstance(section, dict) or "mean" not in section:
            continue
        alphas = alphas or list(section["cvar"])
        cells = [_with_sem(section["mean"], section.get("sem"))] + [
            _with_sem(section["cvar"][a], section.get("cvar_sem", {}).get(a)) for a in alphas]
        lines.append(f"{name:<32}" + "".join(f"{c:>20}" for c in cells)
                     + f"{section['n_tasks']:>7d}{section.get('rollouts', 1):>4d}"
                     + _gain_cell(section.get("adaptation")))
    header = f"{'distribution':<32}{'mean ± sem':>20}" + "".join(
        f"{'cvar_' + a + ' ± sem':>20}" for a in alphas or [])
    header += f"{'tasks':>7}{'R':>4}"
    if any(isinstance(v, dict) and "adaptation" in v for v in report.values()):
        header += f"{'gain ± sem':>20}"
    return "\n".join([f"metric: {report.get('metric')}", header, *lines,
                      *format_curves(report)])


def format_curves(report: dict[str, Any]) -> list[str]:
    """The lines of the report's adaptation curves: each distribution's score (mean ± sem over
    tasks) after 0, 1, ..., k inner steps; none where it has none."""
    curves = {name: section["adaptation_curve"] for name, section in report.items()
              if isinstance(section, dict) and "adaptation_curve" in section}
    if not curves:
        return []
    steps = max(len(curve["mean"]) for curve in curves.values())
    lines = [f"{report.get('metric')} after 0..{steps - 1} inner steps (mean ± sem; the table "
             f"is after the trained number):",
             f"{'distribution':<32}" + "".join(f"{f'{j} step' + ('' if j == 1 else 's'):>20}"
                                               for j in range(steps))]
    for name, curve in curves.items():
        lines.append(f"{name:<32}" + "".join(f"{_with_sem(m, e):>20}"
                                             for m, e in zip(curve["mean"], curve["sem"])))
    return lines


def _gain_cell(adaptation: dict[str, Any] | None) -> str:
    """The adaptation gain ± its standard error, marked where the learner does not adapt."""
    if adaptation is None:
        return ""
    gain, sem = adaptation["gain"], adaptation["gain_sem"]
    return f"{_with_sem(gain, sem):>20}" + ("" if adapts(gain, sem) else "  not adapting")


def _with_sem(value: float, sem: float | None) -> str:
    return f"{value:.4f}" if sem is None else f"{value:.4f} ± {sem:.4f}"


MACHINE_CHARS = 512
"""The longest ``machine`` (:func:`~armeta_rl.devices.machine_name`) a report may record."""


class ReportInvalid(ValueError):
    """An evaluation report (``eval.json``, ``eval_vs_<name>.json``) that cannot be read or fails
    its schema (:func:`check_report`): the run or evaluation that wrote it is not finished."""


def check_report(report: Any, sections: tuple[str, ...] = ("initial",)) -> None:
    """Raise :class:`ReportInvalid` naming the first part of ``report`` (an ``eval.json``'s
    content) that no evaluation can have written.

    It must hold ``metric``, ``benchmark`` and ``method`` (strings) and the distributions
    ``sections``, and a ``machine`` it records must be a short string; every distribution's
    ``mean``, ``cvar`` (α in (0, 1) → value), ``sem`` and ``n_tasks`` must be what
    :func:`~armeta_rl.trainers.evaluation.summarize` makes of
    ``n_tasks`` finite values: finite numbers; each CVaR_α on the worse side of the mean and
    worsening as α grows; and ``sem`` at least the spread that the mean and the tails imply
    (:func:`spread_bound`). A hand-edited mean (``12345``) breaks those relations."""
    if not isinstance(report, dict):
        raise ReportInvalid("it is not a JSON object")
    for name in ("metric", "benchmark", "method"):
        if not isinstance(report.get(name), str):
            raise ReportInvalid(f"'{name}' is missing or not a string")
    for name in sections:
        if not isinstance(report.get(name), dict):
            raise ReportInvalid(f"it has no '{name}' distribution" if name not in report else
                                f"'{name}' = {report[name]!r} is not a distribution's section")
    if "seed" in report and (not isinstance(report["seed"], int)
                             or isinstance(report["seed"], bool)):
        raise ReportInvalid(f"'seed' = {report['seed']!r} is not an integer")
    if "config_sha256" in report and not isinstance(report["config_sha256"], str):
        raise ReportInvalid(f"'config_sha256' = {report['config_sha256']!r} is not a digest")
    if "machine" in report and not (isinstance(report["machine"], str)
                                    and len(report["machine"]) <= MACHINE_CHARS):
        raise ReportInvalid(f"'machine' is not a machine's name (a string of at most "
                            f"{MACHINE_CHARS} characters)")
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
    for key in ("entropy", "kl_p0", "kl_p0_sem"):  # null where undefined (a shift's support
        if section.get(key) is not None and not _number(section[key]):  # is not p0's)
            raise ReportInvalid(f"'{name}.{key}' = {section[key]!r} is not a finite number")
    if "adaptation" in section:
        _check_adaptation(name, section["adaptation"], n)
    if "goal" in section:
        _check_goal(name, section["goal"])
    _check_quarters(name, section)
    if "adaptation_curve" in section:
        _check_curve(name, section["adaptation_curve"], n)
    per_task = section.get("per_task")
    if per_task is not None and not (isinstance(per_task, list) and len(per_task) == n
                                     and all(_number(v) for v in per_task)):
        raise ReportInvalid(f"'{name}.per_task' is not {n} finite task scores")
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


def _check_adaptation(name: str, adaptation: Any, n: int) -> None:
    """The ``adaptation`` of a section must be what :func:`adaptation_gain` makes of ``n``
    tasks."""
    if not isinstance(adaptation, dict):
        raise ReportInvalid(f"'{name}.adaptation' is not an object")
    for key in ("before", "gain"):
        if not _number(adaptation.get(key)):
            raise ReportInvalid(f"'{name}.adaptation.{key}' = {adaptation.get(key)!r} is not a "
                                "finite number")
    for key in ("before_sem", "gain_sem"):
        sem = adaptation.get(key)
        if (sem is None) != (n == 1) or (sem is not None and not (_number(sem) and sem >= 0)):
            raise ReportInvalid(f"'{name}.adaptation.{key}' = {sem!r} is not a standard error "
                                f"of {n} tasks")
    improved = adaptation.get("improved")
    if not isinstance(improved, int) or isinstance(improved, bool) or not 0 <= improved <= n:
        raise ReportInvalid(f"'{name}.adaptation.improved' = {improved!r} is not a count of "
                            f"tasks in [0, {n}]")


def _check_goal(name: str, goal: Any) -> None:
    """The ``goal`` of a section must be what :func:`goal_section` makes: finite mean goal
    terms, the blind one no better than the oracle's, and a share with a non-negative error (or
    both null)."""
    if not isinstance(goal, dict):
        raise ReportInvalid(f"'{name}.goal' is not an object")
    for key in ("achieved", "blind", "oracle"):
        if not _number(goal.get(key)):
            raise ReportInvalid(f"'{name}.goal.{key}' = {goal.get(key)!r} is not a finite number")
    if goal["blind"] > goal["oracle"] + _slack(goal["blind"], goal["oracle"]):
        raise ReportInvalid(f"'{name}.goal.blind' = {goal['blind']!r} is better than the "
                            f"oracle's {goal['oracle']!r}")
    share, sem = goal.get("gap_closed"), goal.get("gap_closed_sem")
    if share is not None and not _number(share):
        raise ReportInvalid(f"'{name}.goal.gap_closed' = {share!r} is not a finite number")
    if sem is not None and not (_number(sem) and sem >= 0):
        raise ReportInvalid(f"'{name}.goal.gap_closed_sem' = {sem!r} is not a standard error")


def _check_quarters(name: str, section: dict[str, Any]) -> None:
    """A section's ``quarter_mass`` must be 4 shares in [0, 1] summing to 1, its
    ``quarter_scores`` 4 finite numbers or nulls (a quarter without tasks)."""
    mass = section.get("quarter_mass")
    if mass is not None and not (
            isinstance(mass, list) and len(mass) == 4
            and all(_number(m) and 0 <= m <= 1 for m in mass)
            and abs(math.fsum(mass) - 1) < 1e-6):
        raise ReportInvalid(f"'{name}.quarter_mass' = {mass!r} is not the mass of 4 quarters")
    scores = section.get("quarter_scores")
    if scores is not None and not (
            isinstance(scores, list) and len(scores) == 4
            and all(v is None or _number(v) for v in scores)):
        raise ReportInvalid(f"'{name}.quarter_scores' = {scores!r} is not 4 quarters' scores")


def _check_curve(name: str, curve: Any, n: int) -> None:
    """The ``adaptation_curve`` of a section must be what :func:`curve_summary` makes of ``n``
    tasks: a finite mean and a standard error at each of 0, 1, ..., k inner steps."""
    where = f"'{name}.adaptation_curve'"
    if not isinstance(curve, dict):
        raise ReportInvalid(f"{where} is not an object")
    steps, means, sems = (curve.get(key) for key in ("inner_steps", "mean", "sem"))
    if not (isinstance(steps, list) and len(steps) >= 2 and steps == list(range(len(steps)))):
        raise ReportInvalid(f"{where}.inner_steps = {steps!r} is not 0, 1, ..., k")
    if not (isinstance(means, list) and len(means) == len(steps) and all(map(_number, means))):
        raise ReportInvalid(f"{where}.mean is not {len(steps)} finite numbers")
    if not (isinstance(sems, list) and len(sems) == len(steps) and all(
            (sem is None) == (n == 1) and (sem is None or _number(sem) and sem >= 0)
            for sem in sems)):
        raise ReportInvalid(f"{where}.sem is not {len(steps)} standard errors of {n} tasks")


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


def read_report(path: Path, sections: tuple[str, ...] = ("initial",),
                below: Path | None = None) -> dict[str, Any]:
    """The evaluation report at ``path`` if it passes :func:`check_report`; at most
    :data:`REPORT_BYTES` are read, from a regular file of one link reached from ``below``
    through no link (:func:`~armeta_rl.run_files.read_file`).

    Raises:
        ReportInvalid: ``path`` is missing, not such a file (a link, a device, a pipe), larger
            than a report can be, unreadable, not UTF-8 JSON, or fails the schema.
    """
    try:
        report = json.loads(read_text(path, REPORT_BYTES, below))
    except FileNotFoundError:
        raise ReportInvalid("it does not exist") from None
    except FileRefused as error:
        raise ReportInvalid(f"it {error.reason}") from None
    except (OSError, ValueError) as error:
        raise ReportInvalid(f"it cannot be read: {' '.join(str(error).split())}") from None
    check_report(report, sections)
    return report
