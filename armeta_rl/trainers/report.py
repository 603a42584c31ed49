"""``eval.json``: the trained leader scored on p0 and on an adversarial distribution, with each
distribution's entropy and KL from p0; and the same for any saved learner against any saved
adversary and on the benchmark's shift suite (``armeta-eval``)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from armeta_rl.collectors.regression import NoisySupport
from armeta_rl.config import TrainConfig
from armeta_rl.devices import CPU, forked_rng, machine_name
from armeta_rl.errors import ConfigError
from armeta_rl.tasks import TaskDistribution
from armeta_rl.tasks.shifts import shift_seed, suite_shifts
from armeta_rl.trainers.checkpoint import run_identity, saved_identity
from armeta_rl.trainers.evaluation import evaluate_on
from armeta_rl.trainers.players import Players, restore_players

EVAL_FILE = "eval.json"


SHIFT_PREFIX = "shift/"
"""A shift's section in a report: ``shift/<name>``."""


def evaluate_players(
    config: TrainConfig, players: Players, adversary: TaskDistribution | None = None,
    shifts: dict[str, TaskDistribution] | None = None, initial: bool = True,
) -> dict[str, Any]:
    """``eval.json``'s content: the leader on p0 (unless ``initial`` is false), on an
    adversarial distribution and on ``shifts`` (named distributions, each its section
    ``shift/<name>``), with the run's ``eval`` settings (every task scored on ``eval.rollouts``
    rollouts); with ``eval.support_noise`` σ > 0 also with N(0, σ²) noise on the support labels
    (the paper's random perturbation test).

    ``adversary`` defaults to the run's own p_φ (AR methods); ERM-style runs have none unless one
    is given (``armeta-eval`` scores any learner on any saved adversary). Every section records
    the seed its tasks were drawn under: p0 ``eval.seed``, the adversary ``eval.seed + 1``, a
    shift :func:`~armeta_rl.tasks.shifts.shift_seed`, so two reports of the same benchmark pair
    task by task. ``machine`` names what computed it (:func:`~armeta_rl.devices.machine_name`).
    """
    ev = config.eval
    adversary = adversary if adversary is not None else players.adversary
    distributions = {"initial": (players.initial, ev.seed)} if initial else {}
    if adversary is not None:
        distributions["adversarial"] = (adversary, ev.seed + 1)
    for name, shift in (shifts or {}).items():
        distributions[SHIFT_PREFIX + name] = (shift, shift_seed(ev.seed, name))
    report: dict[str, Any] = {
        "metric": players.leader.metric,
        "benchmark": config.benchmark.name,
        "method": config.method.name,
        "seed": config.seed,
        "machine": machine_name(players.device),
    }
    for name, (distribution, seed) in distributions.items():
        report[name] = evaluate_on(
            players.leader, distribution, players.eval_collector, ev.n_tasks, list(ev.alphas),
            seed, players.device, ev.rollouts, ev.adaptation_steps,
        )
        report[name]["seed"] = seed
        report[name].update(distribution_stats(distribution, players.initial, seed,
                                               device=players.device))
    if ev.support_noise > 0:
        noisy = NoisySupport(players.eval_collector, ev.support_noise)
        report["support_noise"] = ev.support_noise
        for name, (distribution, seed) in distributions.items():
            report[f"{name}_noisy"] = evaluate_on(
                players.leader, distribution, noisy, ev.n_tasks, list(ev.alphas), seed,
                players.device, ev.rollouts,
            )
    return report


def distribution_stats(distribution: TaskDistribution, initial: TaskDistribution, seed: int,
                       samples: int = 4096, device: torch.device = CPU
                       ) -> dict[str, Any]:
    """Entropy H[p], KL(p0 ‖ p) and the KL's standard error of a task distribution on ``device``
    (Monte Carlo with exact log-densities; the paper's entropy table reports H of p0 and of the
    learned p_φ), and its mass in each quarter of the box (``quarter_mass``,
    :meth:`~armeta_rl.tasks.TaskDistribution.quarter_mass`: how much of an adversary sits where
    a learner does worst), all under ``seed`` in a forked RNG. The KL is ``None`` where it is
    infinite: a shift that leaves part of p0's support out."""
    with forked_rng(device), torch.no_grad():
        torch.manual_seed(seed)
        entropy = float(distribution.entropy(samples))
        kl, kl_sem = (float(value) for value in distribution.kl_from(initial, samples))
        mass = distribution.quarter_mass(samples).tolist()
    finite = math.isfinite(kl)
    return {"entropy": entropy, "kl_p0": kl if finite else None,
            "kl_p0_sem": kl_sem if finite else None, "quarter_mass": mass}


def eval_scalars(report: dict[str, Any]) -> dict[str, float]:
    """Dashboard names ``eval/<distribution>/mean``, ``…/sem`` and ``…/cvar_<α>``; in meta-RL
    also ``…/before`` (the score before adaptation), ``…/gain`` (the adaptation gain),
    ``…/after_<j>_steps`` (the adaptation curve) and, where the benchmark knows its goal
    references, ``…/gap_closed`` (the share of the goal-blind gap closed)."""
    scalars = {}
    for name, section in report.items():
        if isinstance(section, dict) and "mean" in section:
            scalars[f"eval/{name}/mean"] = section["mean"]
            if section.get("sem") is not None:
                scalars[f"eval/{name}/sem"] = section["sem"]
            scalars.update({f"eval/{name}/cvar_{a}": v for a, v in section["cvar"].items()})
            if "adaptation" in section:
                scalars[f"eval/{name}/before"] = section["adaptation"]["before"]
                scalars[f"eval/{name}/gain"] = section["adaptation"]["gain"]
            if (section.get("goal") or {}).get("gap_closed") is not None:
                scalars[f"eval/{name}/gap_closed"] = section["goal"]["gap_closed"]
            curve = section.get("adaptation_curve", {})
            scalars.update({f"eval/{name}/after_{step}_steps": value
                            for step, value in zip(curve.get("inner_steps", []),
                                                   curve.get("mean", []))})
    return scalars


def evaluate_runs(
    learner_dir: str | Path,
    learner: TrainConfig,
    adversary_dir: str | Path | None = None,
    adversary: TrainConfig | None = None,
    shifts: str | Sequence[str] | None = None,
    initial: bool = True,
) -> dict[str, Any]:
    """Score the learner saved in ``learner_dir`` on p0, on the adversary saved in
    ``adversary_dir`` (same benchmark) and on ``shifts`` of its benchmark's shift suite
    (``"all"`` or names; :mod:`armeta_rl.tasks.shifts`); ``initial=False`` leaves p0 out.
    ``learner`` and ``adversary`` are the runs' configs as
    :func:`~armeta_rl.trainers.players.saved_run` gives them, on the
    device to evaluate on (with the ``eval.*`` to score by)."""
    players = restore_players(learner_dir, "learner", learner)
    distribution = None
    if adversary_dir is not None and adversary is not None:
        adv_players = restore_players(adversary_dir, "adversary", adversary)
        if adv_players.adversary is None:
            raise ConfigError(
                "adversary",
                str(adversary_dir),
                f"was trained with method {adversary.method.name}, which has no adversary",
            )
        if adv_players.space != players.space:
            raise ConfigError(
                "adversary",
                str(adversary_dir),
                f"its identifier box {adv_players.space} differs from the learner's "
                f"{players.space}",
            )
        distribution = adv_players.adversary
    chosen = None if shifts is None else suite_shifts(
        players.space, learner.benchmark.shift_suite, learner.benchmark.name, shifts)
    report = evaluate_players(learner, players, distribution, chosen, initial)
    identity = saved_identity(learner_dir) or run_identity(learner.values())
    report["config_sha256"] = identity["config_sha256"]
    report["learner"] = str(learner_dir)
    report["adversary"] = None if adversary_dir is None else str(adversary_dir)
    return report
