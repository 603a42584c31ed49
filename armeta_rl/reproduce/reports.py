"""``<experiment>.md`` and its figures, one layout per kind of artefact in the paper.

The experiment's YAML names its ``layout``; each layout writes the Markdown (our numbers, and the
paper's where its YAML holds them under ``paper``) and its PNGs into the results directory.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from armeta_rl.reproduce import figures
from armeta_rl.reproduce.aggregate import (
    INITIAL,
    SHIFT_PREFIX,
    SeedSummary,
    decimals,
    difference_decimals,
    display,
    markdown_table,
    method_curve,
    over_seeds,
    select,
    summary,
)
from armeta_rl.reproduce.curves import (
    LATE_PARTS,
    late_changes,
    late_levels,
    late_means,
    late_parts,
)
from armeta_rl.reproduce.plan import Plan, composed, precision_target, run_command
from armeta_rl.trainers.run_dir import write_text_atomically


def _methods(plan: Plan) -> list[str]:
    return list(dict.fromkeys(run.method for run in plan.runs))


def _benchmarks(plan: Plan) -> list[str]:
    return list(dict.fromkeys(run.benchmark for run in plan.runs))


def _distributions(plan: Plan, records: Sequence[dict[str, Any]] = (),
                   benchmark: str | None = None) -> dict[str, str]:
    """``initial``, the experiment's adversaries, its attacks' adversaries and the shifts the
    records hold (``shift/<name>``, in the order first met; of ``benchmark`` alone if given, as
    each benchmark has its own suite), with their labels."""
    labels = plan.spec.get("labels", {})
    names = [INITIAL, *plan.spec.get("adversaries", {}), *plan.spec.get("attacks", {})]
    names += list(dict.fromkeys(r["distribution"] for r in records
                                if r["distribution"].startswith(SHIFT_PREFIX)
                                and benchmark in (None, r["benchmark"])))
    return {name: labels.get(name, name.replace(SHIFT_PREFIX, "shift: ")) for name in names}


def _cvar_key(plan: Plan) -> str:
    return f"cvar_{float(plan.spec.get('alpha', 0.5))}"


def _cvar_label(plan: Plan) -> str:
    return f"CVaR{float(plan.spec.get('alpha', 0.5))}"


def _cell(value: SeedSummary | None, bold: bool = False, se: bool = False) -> str:
    if value is None:
        return "–"
    text = value.format("se" if se else "std")
    return f"**{text}**" if bold else text


def _best(values: Sequence[SeedSummary | None], higher_better: bool) -> int | None:
    present = [(v.mean, i) for i, v in enumerate(values) if v is not None]
    if len(present) < 2:
        return None
    return (max if higher_better else min)(present)[1]


def _higher_better(records: Sequence[dict[str, Any]]) -> bool:
    return bool(records) and records[0]["metric"] == "return"


def table(plan: Plan, records: list[dict[str, Any]], results: Path) -> str:
    """Table 1 / the CNP table: per benchmark and distribution, the average and CVaR_α of every
    method (mean ± std over seeds), the best of a row in bold, the paper's row beneath."""
    methods, cvar = _methods(plan), _cvar_key(plan)
    alpha = plan.spec.get("alpha", 0.5)
    header = ["Benchmark", "Distribution", *(f"{display(m)} avg" for m in methods),
              *(f"{display(m)} CVaR{alpha}" for m in methods)]
    rows = []
    higher = _higher_better(records)
    paper = plan.spec.get("paper", {})
    for benchmark in _benchmarks(plan):
        for distribution, label in _distributions(plan, records, benchmark).items():
            cells = []
            for column in ("mean", cvar):
                values = [summary(records, column, benchmark=benchmark, method=m,
                                  distribution=distribution, noisy=False) for m in methods]
                best = _best(values, higher)
                cells += [_cell(v, i == best) for i, v in enumerate(values)]
            rows.append([display(benchmark), label, *cells])
            quoted = [paper.get(benchmark, {}).get(m, {}).get(distribution) for m in methods]
            if any(quoted):
                rows.append(["", "paper", *(q[0] if q else "–" for q in quoted),
                             *(q[1] if q else "–" for q in quoted)])
    groups = [(f"{distribution}\n{name}", {"distribution": distribution, "noisy": False}, column)
              for distribution in _distributions(plan, records)
              for name, column in (("avg", "mean"), (f"CVaR{alpha}", cvar))]
    figures.bars(records, _benchmarks(plan), methods, groups, results / f"{plan.experiment}.png",
                 records[0]["metric"])
    return (markdown_table(header, rows) + f"\n\n![{plan.experiment}]({plan.experiment}.png)"
            "\n\nBars: mean over seeds, standard-error bars.")


def cvar_curves(plan: Plan, records: list[dict[str, Any]], results: Path) -> str:
    """CVaR_α for α = 0 … 0.9 per method (figure with standard-error bands), and the curve's
    values at a few α in a table (mean ± s.e. over seeds)."""
    methods, benchmarks, distributions = _methods(plan), _benchmarks(plan), _distributions(plan)
    figures.cvar_curves(records, benchmarks, methods, distributions,
                        results / f"{plan.experiment}.png")
    shown = [float(a) for a in plan.spec.get("table_alphas", [0.0, 0.5, 0.9])]
    rows = []
    for benchmark in benchmarks:
        for distribution, label in distributions.items():
            for method in methods:
                curve = method_curve(records, benchmark, method, distribution)
                if curve is None:
                    continue
                alphas, points = curve
                by_alpha = dict(zip(alphas, points))
                rows.append([display(benchmark), label, display(method),
                             *(_cell(by_alpha.get(a), se=True) for a in shown)])
    header = ["Benchmark", "Distribution", "Method", *(f"CVaR_{a}" for a in shown)]
    return (f"![CVaR curves]({plan.experiment}.png)\n\nMean ± standard error over seeds "
            "(CVaR_0 is the average).\n\n" + markdown_table(header, rows))


def scatter(plan: Plan, records: list[dict[str, Any]], results: Path) -> str:
    """Initial against adversarial average per method and seed, with y = x (figure), and the
    gap adversarial − initial over seeds (table)."""
    methods, benchmarks = _methods(plan), _benchmarks(plan)
    adversaries = {k: v for k, v in _distributions(plan).items() if k != INITIAL}
    figures.scatter(records, benchmarks, methods, adversaries, results / f"{plan.experiment}.png")
    rows = []
    for benchmark in benchmarks:
        for adversary, label in adversaries.items():
            for method in methods:
                pairs = {r["seed"]: r["mean"] for r in select(
                    records, benchmark=benchmark, method=method, distribution=INITIAL,
                    noisy=False)}
                gaps = [r["mean"] - pairs[r["seed"]] for r in select(
                    records, benchmark=benchmark, method=method, distribution=adversary,
                    noisy=False) if r["seed"] in pairs]
                initial = summary(records, "mean", benchmark=benchmark, method=method,
                                  distribution=INITIAL, noisy=False)
                shifted = summary(records, "mean", benchmark=benchmark, method=method,
                                  distribution=adversary, noisy=False)
                gap = summary([{"seed": i, "gap": g} for i, g in enumerate(gaps)], "gap")
                rows.append([display(benchmark), label, display(method), _cell(initial),
                             _cell(shifted), _cell(gap)])
    header = ["Benchmark", "Adversary", "Method", "initial avg", "adversarial avg",
              "gap (adversarial − initial)"]
    return f"![scatter]({plan.experiment}.png)\n\n" + markdown_table(header, rows)


def noise(plan: Plan, records: list[dict[str, Any]], results: Path) -> str:
    """CVaR_α with clean and with noisy support labels per method, on p0 and on the adversary
    (table: mean ± s.e. over seeds; bar chart with standard-error bars)."""
    methods, cvar = _methods(plan), _cvar_key(plan)
    groups = [(f"{label}, {'noisy' if noisy else 'clean'}",
               {"distribution": distribution, "noisy": noisy}, cvar)
              for distribution, label in _distributions(plan).items()
              for noisy in (False, True)]
    figures.bars(records, _benchmarks(plan), methods, groups, results / f"{plan.experiment}.png",
                 _cvar_label(plan))
    table = _grouped_table(plan, records, methods, groups)
    return (f"![{plan.experiment}]({plan.experiment}.png)\n\n{_cvar_label(plan)}, mean ± s.e. "
            "over seeds.\n\n" + table)


def _grouped_table(plan: Plan, records: list[dict[str, Any]], methods: list[str],
                   groups: list[tuple[str, dict[str, Any], str]]) -> str:
    """A Markdown table, a row per benchmark and method and a column per group (its label, the
    records it selects, the column it summarizes), cells mean ± s.e. over seeds."""
    rows = [[display(benchmark), display(method), *(
        _cell(summary(records, column, benchmark=benchmark, method=method, **where), se=True)
        for _, where, column in groups)]
        for benchmark in _benchmarks(plan) for method in methods]
    return markdown_table(["Benchmark", "Method", *(label for label, _, _ in groups)], rows)


def bar_chart(plan: Plan, records: list[dict[str, Any]], results: Path) -> str:
    """Meta-RL figures: average and CVaR_α returns on p0 and on the adversaries per method (bars
    with standard-error bars; table: mean ± s.e. over seeds)."""
    methods, cvar = _methods(plan), _cvar_key(plan)
    groups = [(f"{label}, {name}", {"distribution": distribution, "noisy": False}, column)
              for distribution, label in _distributions(plan, records).items()
              for name, column in (("average", "mean"), (_cvar_label(plan), cvar))]
    figures.bars(records, _benchmarks(plan), methods, groups, results / f"{plan.experiment}.png",
                 "return")
    table = _grouped_table(plan, records, methods, groups)
    return (f"![{plan.experiment}]({plan.experiment}.png)\n\nReturns, mean ± s.e. over seeds."
            "\n\n" + table)


def _lambda(plan: Plan, variant: str) -> float:
    """λ of a variant: the value of its ``risk.ar.lam=`` override."""
    for group in plan.spec["groups"]:
        for override in group.get("variants", {}).get(variant, []):
            if override.startswith("risk.ar.lam="):
                return float(override.split("=", 1)[1])
    raise ValueError(f"variant {variant!r} sets no risk.ar.lam")


def entropy(plan: Plan, records: list[dict[str, Any]], results: Path) -> str:
    """The entropy table (H of p0 and of p_φ per λ; KL(p0 ‖ p_φ) too), MSE against λ (figure and
    table) and the adversaries' density maps at every λ (seed of the first run)."""
    variants = list(dict.fromkeys(run.variant for run in plan.runs))
    lambdas = {v: _lambda(plan, v) for v in variants}
    method = _methods(plan)[0]
    paper = plan.spec.get("paper", {})
    header = ["Benchmark", "Distribution", *(f"λ = {lambdas[v]}" for v in variants)]
    rows = []
    for benchmark in _benchmarks(plan):
        for distribution, key, name in ((INITIAL, "entropy", "H[p0]"),
                                        ("same_seed", "entropy", "H[p_φ]"),
                                        ("same_seed", "kl_p0", "KL(p0 ‖ p_φ)")):
            rows.append([display(benchmark), name, *(
                _cell(summary(records, key, benchmark=benchmark, method=method, variant=v,
                              distribution=distribution, noisy=False)) for v in variants)])
            quoted = paper.get(benchmark, {}).get(name)
            if quoted:
                rows.append(["", "paper", *quoted])
    cvar = _cvar_key(plan)
    columns = {"mean": "average", cvar: _cvar_label(plan)}
    figures.lambda_curves(records, _benchmarks(plan), method, lambdas, columns,
                          results / f"{plan.experiment}_lambda.png")
    mse_rows = []
    for benchmark in _benchmarks(plan):
        for v in variants:
            mse_rows.append([display(benchmark), str(lambdas[v]), *(
                _cell(summary(records, column, benchmark=benchmark, method=method, variant=v,
                              distribution=distribution, noisy=False), se=True)
                for distribution in (INITIAL, "same_seed") for column in columns)])
    mse_header = ["Benchmark", "λ", *(f"{d} {c}" for d in ("initial", "adversarial")
                                      for c in columns.values())]
    seed = min(run.seed for run in plan.runs)
    images = {(run.benchmark, f"λ = {lambdas[run.variant]}"):
              results / run.subdir / "density.png" for run in plan.runs
              if run.seed == seed and (results / run.subdir / "density.png").is_file()}
    if images:  # packed runs keep no density map: their figure stays as it was drawn
        figures.image_grid(images, _benchmarks(plan), [f"λ = {lambdas[v]}" for v in variants],
                           results / f"{plan.experiment}_densities.png")
    return (markdown_table(header, rows) + f"\n\n![MSE against λ]({plan.experiment}_lambda.png)"
            f"\n\nMean ± s.e. over seeds.\n\n" + markdown_table(mse_header, mse_rows)
            + f"\n\n![densities]({plan.experiment}_densities.png)\n\nDensity maps: seed {seed}, "
            "p_φ (left) beside p0 (right) in each panel.")


Learner = tuple[str, str]
"""A learner column of a paired report: (method, variant)."""


def _learners(plan: Plan) -> list[Learner]:
    return list(dict.fromkeys((run.method, run.variant) for run in plan.runs))


def learner_label(plan: Plan, learner: Learner) -> str:
    """``AR-MAML``, or the experiment's label of a learner (``learner_labels: {ar_maml-best:
    …}``)."""
    method, variant = learner
    name = method if not variant else f"{method}-{variant}"
    return plan.spec.get("learner_labels", {}).get(name, display(method) + (
        f" [{variant}]" if variant else ""))


def _level(records: list[dict[str, Any]], column: str, sem_column: str, **where: Any) -> str:
    """``mean ± std`` over seeds of ``column``, with the root-mean-square over seeds of its
    standard error over tasks in brackets."""
    chosen = [r for r in select(records, **where) if r.get(column) is not None]
    if not chosen:
        return "–"
    text = over_seeds([r[column] for r in chosen]).format()
    sems = [r[sem_column] for r in chosen if r.get(sem_column) not in (None, "")]
    if sems:
        text += f" [{(sum(s * s for s in sems) / len(sems)) ** 0.5:.{_places(text)}f}]"
    return text


def _places(text: str) -> int:
    number = text.split(" ")[0]
    return len(number.split(".")[1]) if "." in number else 0


def paired_seeds(records: list[dict[str, Any]], learner: Learner, reference: Learner,
                 alpha: float, **where: Any) -> list[dict[str, Any]]:
    """Per seed, ``learner`` minus ``reference`` on the same tasks (same task seed and count in
    both records: :func:`~armeta_rl.trainers.evaluation.paired_difference`); seeds where either
    has not finished, or whose records were not scored on the same tasks, are left out."""
    from armeta_rl.trainers.evaluation import paired_difference

    theirs = {r["seed"]: r for r in select(records, method=reference[0], variant=reference[1],
                                           **where)}
    pairs = []
    for ours in select(records, method=learner[0], variant=learner[1], **where):
        ref = theirs.get(ours["seed"])
        if ref is None or not ours.get("per_task") or not ref.get("per_task") or (
                ours["task_seed"], ours["n_tasks"]) != (ref["task_seed"], ref["n_tasks"]):
            continue
        diff = paired_difference(ours["per_task"], ref["per_task"], ours["metric"], [alpha])
        pairs.append({"seed": ours["seed"], "mean": diff["mean"], "sem": diff["sem"],
                      "cvar": diff["cvar"][str(alpha)], "cvar_sem": diff["cvar_sem"][str(alpha)]})
    return pairs


def _reference_scale(records: list[dict[str, Any]], reference: Learner, **where: Any) -> float:
    """``reference``'s average over seeds on ``where`` (NaN where it has no record there): the
    size of the returns a paired difference to it compares, whose decimals the difference takes
    (:func:`~armeta_rl.reproduce.aggregate.difference_decimals`)."""
    values = [r["mean"] for r in select(records, method=reference[0], variant=reference[1],
                                         **where)]
    return over_seeds(values).mean if values else math.nan


def _difference(pairs: list[dict[str, Any]], column: str, higher_better: bool,
                scale: float) -> str:
    """Paired differences over seeds: ``mean ± std [RMS task s.e.] (k/S better)``, in bold when
    the mean lies beyond twice its standard error over seeds; with the decimals of the values of
    size ``scale`` they compare (:func:`~armeta_rl.reproduce.aggregate.difference_decimals`)."""
    if not pairs:
        return "–"
    values = [p[column] for p in pairs]
    spread = over_seeds(values)
    places = difference_decimals(scale, spread.std if spread.n > 1 else math.nan)
    text = f"{spread.mean:+.{places}f}"
    if spread.n > 1:
        text += f" ± {spread.std:.{places}f}"
    sems = [p[f"{column}_sem" if column == "cvar" else "sem"] for p in pairs]
    sems = [s for s in sems if s is not None]
    if sems:
        text += f" [{(sum(s * s for s in sems) / len(sems)) ** 0.5:.{places}f}]"
    better = sum((v > 0) == higher_better and v != 0 for v in values)
    text += f" ({better}/{len(values)})"
    beyond = spread.n > 1 and abs(spread.mean) > 2 * spread.se
    return f"**{text}**" if beyond else text


def _gain(records: list[dict[str, Any]], **where: Any) -> tuple[str, int, int]:
    """The adaptation gain over seeds, ``+mean ± std [RMS s.e. over tasks] (k/S adapt)``, with k
    the seeds whose gain is beyond twice its standard error over tasks
    (:func:`~armeta_rl.trainers.evaluation.adapts`); and k and S. Written with the decimals of
    the returns it is a difference of, so the cells of one table agree."""
    from armeta_rl.trainers.evaluation import adapts

    chosen = [r for r in select(records, **where) if r.get("gain") is not None]
    if not chosen:
        return "–", 0, 0
    spread = over_seeds([r["gain"] for r in chosen])
    places = decimals(over_seeds([r["mean"] for r in chosen]).mean)  # the return's decimals
    text = f"{spread.mean:+.{places}f}" + (f" ± {spread.std:.{places}f}" if spread.n > 1 else "")
    sems = [r["gain_sem"] for r in chosen if r.get("gain_sem") is not None]
    if sems:
        text += f" [{(sum(e * e for e in sems) / len(sems)) ** 0.5:.{places}f}]"
    adapting = sum(adapts(r["gain"], r.get("gain_sem")) for r in chosen)
    return f"{text} ({adapting}/{len(chosen)} adapt)", adapting, len(chosen)


def adaptation_section(plan: Plan, records: list[dict[str, Any]]) -> str:
    """Meta-RL: every learner's adaptation gain (return after the inner step − before, paired on
    the same episodes) per distribution, and which learners do not adapt on p0: a learner with
    a seed whose gain is not beyond twice its standard error over tasks is marked, since a
    comparison between learners that do not adapt says nothing about robust meta-learning.
    Empty where no record holds a gain."""
    if not any(r.get("gain") is not None for r in records):
        return ""
    learners = _learners(plan)
    rows, idle = [], []
    for benchmark in _benchmarks(plan):
        for distribution, label in _distributions(plan, records, benchmark).items():
            cells = [_gain(records, benchmark=benchmark, method=m, variant=v,
                           distribution=distribution, noisy=False) for m, v in learners]
            rows.append([display(benchmark), label, *(cell for cell, _, _ in cells)])
            if distribution == INITIAL:
                idle += [f"{learner_label(plan, learner)} on {display(benchmark)} "
                         f"({k}/{n} seeds adapt)"
                         for learner, (_, k, n) in zip(learners, cells) if n and k < n]
    header = ["Benchmark", "Distribution", *(learner_label(plan, lr) for lr in learners)]
    verdict = ("**Every learner adapts on p0** at every finished seed (its gain beyond twice "
               "its standard error over tasks)." if not idle else
               "**Not adapting on p0** (a seed adapts when its gain is beyond twice its "
               "standard error over tasks): " + "; ".join(idle) + ". A comparison between "
               "learners that do not adapt compares policies, not meta-learners: it is no "
               "robustness result.")
    gap = gap_closed_section(plan, records)
    return ("**Adaptation gain**: return after the inner step minus return before it, on the "
            "same episodes, mean ± std over seeds [root-mean-square over seeds of its "
            "standard error over tasks] (seeds whose gain is beyond twice that error / "
            "seeds).\n\n" + markdown_table(header, rows) + "\n\n" + verdict
            + ("\n\n" + gap if gap else ""))


def _share(records: list[dict[str, Any]], **where: Any) -> str:
    """The share of the goal-blind gap closed over seeds, in percent: ``mean ± std [RMS s.e.
    over tasks]``; "–" where no seed's evaluation recorded the references, or where a seed's
    share is undefined (:func:`~armeta_rl.trainers.evaluation.share_resolved`: no gap to speak
    of on these tasks; the other seeds' shares alone would be a selection)."""
    chosen = [r for r in select(records, **where) if r.get("goal_oracle") is not None]
    if not chosen or any(r.get("gap_closed") is None for r in chosen):
        return "–"
    spread = over_seeds([100 * r["gap_closed"] for r in chosen])
    text = f"{spread.mean:.0f} %" if spread.n < 2 else f"{spread.mean:.0f} ± {spread.std:.0f} %"
    sems = [100 * r["gap_closed_sem"] for r in chosen]
    text += f" [{(sum(e * e for e in sems) / len(sems)) ** 0.5:.0f}]"
    return text


def gap_closed_section(plan: Plan, records: list[dict[str, Any]]) -> str:
    """Meta-RL: every learner's share of the goal-blind gap closed per distribution, (R_adapted
    − R_blind) / (R_oracle − R_blind) on the distribution's evaluation tasks
    (:func:`~armeta_rl.trainers.evaluation.gap_closed`; the references: docs/meta-rl.md), so
    that a gain reads against what the goal is worth; undefined where the gap is too small for
    it to mean anything (:func:`~armeta_rl.trainers.evaluation.share_resolved`). Empty where no
    evaluation recorded the references (a benchmark without them, or evaluations made before
    they were recorded)."""
    if not any(r.get("goal_oracle") is not None for r in records):
        return ""
    learners = _learners(plan)
    rows = [[display(benchmark), label, *(
        _share(records, benchmark=benchmark, method=m, variant=v, distribution=distribution,
               noisy=False) for m, v in learners)]
        for benchmark in _benchmarks(plan)
        for distribution, label in _distributions(plan, records, benchmark).items()]
    header = ["Benchmark", "Distribution", *(learner_label(plan, lr) for lr in learners)]
    return ("**Share of the goal-blind gap closed**: (R_adapted − R_blind) / (R_oracle − "
            "R_blind) of the goal term on each distribution's evaluation tasks, R_blind the "
            "best goal-blind policy for those tasks and R_oracle the best with the goal known "
            "(0 %: no better than ignoring the goal; 100 %: as good as knowing it), mean ± std "
            "over seeds [root-mean-square over seeds of its standard error over tasks]; – "
            "where the evaluation predates the references, and where a seed's share has a "
            "standard error over tasks above 100 points: there the gap R_oracle − R_blind is "
            "under one standard error of what it divides, too small for the share to mean "
            "anything (a distribution concentrated on one goal, where the best goal-blind "
            "policy is the oracle).\n\n"
            + markdown_table(header, rows))


def paired(plan: Plan, records: list[dict[str, Any]], results: Path) -> str:
    """Meta-RL reports (docs/meta-rl.md): every learner's average and CVaR_α on p0, the
    adversaries and the shift suite (mean ± std over seeds [standard error over tasks]), then
    each learner minus the reference learner (``paired: {against: <method>}``) on the same tasks
    and random streams, per seed, summarized over seeds; figures of both. Before them the
    adaptation gain and the share of the goal-blind gap closed (:func:`adaptation_section`);
    after them each learner's verdicts by the docs' rule (:func:`verdict_lines`, also written to
    ``<experiment>_verdicts.md``, with each attack's check, :func:`attack_check`, so that pages
    quoting them copy no number by hand) and the adversaries' strength
    (:func:`adversary_section`)."""
    learners, cvar, alpha = _learners(plan), _cvar_key(plan), float(plan.spec.get("alpha", 0.5))
    reference = (plan.spec.get("paired", {}).get("against", learners[0][0]), "")
    distributions = _distributions(plan, records)
    higher = _higher_better(records)
    labels = [learner_label(plan, learner) for learner in learners]
    level_rows, diff_rows = [], []
    for benchmark in _benchmarks(plan):
        for distribution, label in _distributions(plan, records, benchmark).items():
            where = {"benchmark": benchmark, "distribution": distribution, "noisy": False}
            level_rows.append([display(benchmark), label, *(
                _level(records, column, sem, method=m, variant=v, **where)
                for column, sem in (("mean", "sem"), (cvar, f"cvar_sem_{alpha}"))
                for m, v in learners)])
            others = [learner for learner in learners if learner != reference]
            pairs = {learner: paired_seeds(records, learner, reference, alpha, **where)
                     for learner in others}
            scale = _reference_scale(records, reference, **where)
            diff_rows.append([display(benchmark), label, *(
                _difference(pairs[learner], column, higher, scale)
                for column in ("mean", "cvar") for learner in others)])
    cvar_label = _cvar_label(plan)
    level_header = ["Benchmark", "Distribution", *(f"{name} avg" for name in labels),
                    *(f"{name} {cvar_label}" for name in labels)]
    others = [learner_label(plan, learner) for learner in learners if learner != reference]
    diff_header = ["Benchmark", "Distribution", *(f"{name} Δavg" for name in others),
                   *(f"{name} Δ{cvar_label}" for name in others)]
    key = [{**r, "method": learner_label(plan, (r["method"], r["variant"]))} for r in records]
    groups = [(f"{label}, {name}", {"distribution": distribution, "noisy": False}, column)
              for distribution, label in distributions.items()
              for name, column in (("average", "mean"), (cvar_label, cvar))]
    figures.bars(key, _benchmarks(plan), labels, groups, results / f"{plan.experiment}.png",
                 records[0]["metric"])
    reference_label = learner_label(plan, reference)
    better = "higher" if higher else "lower"
    adaptation = adaptation_section(plan, records)
    progress = progress_line(plan, records, reference)
    verdicts = verdict_lines(plan, records, reference, alpha) + ([progress] if progress else [])
    checks = [check for benchmark in _benchmarks(plan)
              for check in attack_check(plan, records, benchmark)]
    write_text_atomically(verdicts_path(results, plan.experiment),
                          "\n".join(verdicts + [f"- {check}" for check in checks]) + "\n")
    adversaries = adversary_section(plan, records)
    precision = precision_line(plan, records, reference, alpha)
    return ((adaptation + "\n\n" if adaptation else "")
            + markdown_table(level_header, level_rows)
            + f"\n\n![{plan.experiment}]({plan.experiment}.png)\n\nBars: mean over seeds, "
            "standard-error bars over seeds.\n\n"
            f"**Paired differences against {reference_label}**, on the same tasks and random "
            f"streams: each learner minus {reference_label} per seed ({better} is better for "
            f"the learner), mean ± std over seeds, [root-mean-square over seeds of the paired "
            f"standard error over tasks], (seeds where the learner is better / seeds). Bold: "
            "the mean is more than twice its standard error over seeds from 0.\n\n"
            + markdown_table(diff_header, diff_rows)
            + (f"\n\n{precision}" if precision else "")
            + f"\n\n**In short, by the rule** (docs/meta-rl.md, \"Results\"): a learner "
            f"*helps* on a distribution when its paired difference to {reference_label} is "
            "on the better side, beyond twice its standard error over seeds and better on at "
            "least 80 % of the seeds; it *hurts* when the same holds on the worse side; "
            f"otherwise it *does not help* (average and {_cvar_label(plan)} each: the mean "
            "paired difference ± its standard error over seeds, and the seeds where the "
            f"learner is better; also in `{verdicts_path(results, plan.experiment).name}`):\n\n"
            + "\n".join(verdicts)
            + ("\n\n" + adversaries if adversaries else "")
            + "".join(f"\n\n{check}" for check in checks))


def precision_line(plan: Plan, records: list[dict[str, Any]], reference: Learner,
                   alpha: float) -> str:
    """The protocol's precision check (:func:`~armeta_rl.reproduce.plan.precision_target`): per
    learner other than ``reference``, the largest standard error over seeds of its paired
    differences (average and CVaR_α) on the target's distributions, whether it is below the
    target, and otherwise how many seeds would bring it there at the spread so far (se = std/√n
    < s once n > (std/s)²), saying whether the plan's seeds are all in (*not met*) or more are
    to come (*not yet*); empty for an experiment without a target."""
    target = precision_target(plan.spec)
    if target is None:
        return ""
    bound, names = target
    labels = {**_distributions(plan, records), INITIAL: "p0"}
    benchmarks = _benchmarks(plan)
    columns = (("mean", "avg"), ("cvar", _cvar_label(plan)))
    planned = len({run.seed for run in plan.runs})
    parts = []
    for learner in _learners(plan):
        if learner == reference:
            continue
        spreads = []
        for benchmark, name in ((b, n) for b in benchmarks for n in names):
            pairs = paired_seeds(records, learner, reference, alpha, benchmark=benchmark,
                                 distribution=name, noisy=False)
            where = labels.get(name, name) + (f" of {display(benchmark)}"
                                              if len(benchmarks) > 1 else "")
            spreads += [(over_seeds([p[column] for p in pairs]), f"{where}, {shown}")
                        for column, shown in columns if len(pairs) > 1]
        label = learner_label(plan, learner)
        if not spreads:
            parts.append(f"{label}: fewer than two seeds paired")
            continue
        spread, where = max(spreads, key=lambda item: item[0].se)
        if spread.se < bound:
            status = "reached"
        else:
            missed = (f"not met at the planned {planned} seeds" if spread.n >= planned
                      else "not yet")
            wanted = math.floor((spread.std / bound) ** 2) + 1
            status = f"{missed}; at this spread {wanted} seeds would reach it"
        parts.append(f"{label}: largest {spread.se:.2f} ({where}; {spread.n} seeds), {status}")
    shown = ", ".join(labels.get(name, name) for name in names)
    return (f"**Precision**, the protocol's target: the paired standard error over seeds below "
            f"{bound:g} on {shown}. " + "; ".join(parts) + ".")


HELPS, HURTS, NO_HELP = "helps", "hurts", "does not help"
"""The three verdicts of the docs' rule (:func:`verdict`)."""
SEED_SHARE = (4, 5)
"""The least share of seeds on which a learner must be better (worse) to help (hurt): 4 of 5,
80 % of the seeds."""


def seeds_on_each_side(values: Sequence[float], higher_better: bool) -> tuple[int, int]:
    """How many of the paired differences ``values`` are on the learner's better side and how
    many on its worse side (a difference of exactly 0 on neither)."""
    better = sum((v > 0) == higher_better and v != 0 for v in values)
    worse = sum((v < 0) == higher_better and v != 0 for v in values)
    return better, worse


def verdict(values: Sequence[float], higher_better: bool) -> str:
    """The docs' rule (docs/meta-rl.md, "Results") on one learner's paired differences to the
    reference learner over seeds ``values``: :data:`HELPS` when their mean is on the better side
    and beyond twice its standard error over seeds and the learner is better on at least
    :data:`SEED_SHARE` of the seeds, :data:`HURTS` when the same holds on the worse side,
    :data:`NO_HELP` otherwise (one seed: no standard error, no verdict but this)."""
    spread = over_seeds(values) if values else None
    if spread is None or spread.n < 2 or not abs(spread.mean) > 2 * spread.se:
        return NO_HELP
    better, worse = seeds_on_each_side(values, higher_better)
    share, of = SEED_SHARE
    if (spread.mean > 0) == higher_better:
        return HELPS if better * of >= share * len(values) else NO_HELP
    return HURTS if worse * of >= share * len(values) else NO_HELP


def verdicts_path(results: Path, experiment: str) -> Path:
    """``<results>/<experiment>_verdicts.md``: the report's verdicts alone, for pages that
    include them (docs/meta-rl.md)."""
    return results / f"{experiment}_verdicts.md"


def _finding(values: Sequence[float], name: str, higher_better: bool, scale: float) -> str:
    """``avg +1.3 ± 0.5, 5/5 seeds better`` of paired differences over seeds: their mean ± its
    standard error over seeds (the error :func:`verdict` weighs, not the tables' std), with the
    decimals of the values of size ``scale`` they compare, as in the report's tables."""
    spread = over_seeds(values)
    places = difference_decimals(scale, spread.se)
    better, _ = seeds_on_each_side(values, higher_better)
    return (f"{name} {spread.mean:+.{places}f} ± {spread.se:.{places}f}, "
            f"{better}/{len(values)} seeds better")


def verdict_lines(plan: Plan, records: list[dict[str, Any]], reference: Learner,
                  alpha: float) -> list[str]:
    """One Markdown bullet per learner other than ``reference``: where it helps and where it
    hurts by :func:`verdict` (average and CVaR_α, with its paired difference over seeds and the
    seeds on which it is better), on how many distributions it does not help, which of those it
    is better or worse on at every seed within the spread, where it has no verdict yet (paired
    at one seed only: no standard error over seeds), and, for a learner that does not
    adapt on p0 at every seed, that the comparison is no robustness result; generated from the
    records, so that prose and tables cannot drift."""
    higher = _higher_better(records)
    benchmarks = _benchmarks(plan)
    lines = []
    for learner in _learners(plan):
        if learner == reference:
            continue
        found: dict[str, list[str]] = {HELPS: [], HURTS: [], "better": [], "worse": []}
        compared = seeds = 0
        neutral: list[str] = []
        single: list[str] = []  # paired at one seed: no standard error over seeds, no verdict
        for benchmark in benchmarks:
            for distribution, label in _distributions(plan, records, benchmark).items():
                pairs = paired_seeds(records, learner, reference, alpha, benchmark=benchmark,
                                     distribution=distribution, noisy=False)
                if not pairs:
                    continue
                seeds = max(seeds, len(pairs))
                where = "p0" if distribution == INITIAL else label
                if len(benchmarks) > 1:
                    where = f"{display(benchmark)} {where}"
                if len(pairs) < 2:
                    single.append(where)
                    continue
                compared += 1
                scale = _reference_scale(records, reference, benchmark=benchmark,
                                         distribution=distribution, noisy=False)
                judged: dict[str, list[str]] = {key: [] for key in found}
                for column, name in (("mean", "avg"), ("cvar", _cvar_label(plan))):
                    values = [p[column] for p in pairs]
                    outcome = verdict(values, higher)
                    better, worse = seeds_on_each_side(values, higher)
                    if outcome == NO_HELP and len(values) > 1 and len(values) in (better, worse):
                        outcome = "better" if better else "worse"  # unanimous, within spread
                    if outcome != NO_HELP:
                        judged[outcome].append(_finding(values, name, higher, scale))
                is_neutral = not (judged[HELPS] or judged[HURTS])
                for outcome, findings in judged.items():
                    if findings and (is_neutral or outcome in (HELPS, HURTS)):
                        found[outcome].append(f"{where} ({'; '.join(findings)})")
                if is_neutral:
                    neutral.append(where)
        name = f"- **{learner_label(plan, learner)}**"
        if seeds < 2:
            lines.append(f"{name} ({seeds} seed{'s' if seeds != 1 else ''} paired with "
                         f"{learner_label(plan, reference)}): no verdict, as the rule needs "
                         "a standard error over at least two seeds.")
            continue
        parts = [f"{outcome} on {', '.join(found[outcome])}" for outcome in (HELPS, HURTS)
                 if found[outcome]]
        if neutral:
            unanimous = [f"{side} than {learner_label(plan, reference)} at every seed on "
                         f"{', '.join(found[side])}" for side in ("better", "worse")
                         if found[side]]
            parts.append((f"does not help on the other {_count(len(neutral), 'distribution')}"
                          if parts else "does not help on "
                          + (neutral[0] if compared == 1 else
                             f"any of the {compared} distributions"))
                         + (f", though it is {' and '.join(unanimous)}, within the spread"
                            if unanimous else ""))
        if single:
            where = (" and ".join(single) if len(single) <= 2 else
                     f"the other {_count(len(single), 'distribution')}")
            parts.append(f"no verdict yet on {where}, paired at one seed only")
        text = f"{name} ({seeds} seeds): " + "; ".join(parts)
        lines.append(text + "." + _adaptation_caveat(plan, records, learner))
    return lines


PROGRESS_WORDS = {HELPS: "ahead", HURTS: "behind", NO_HELP: "level"}
"""A learner's p0 gain against the reference's by :func:`verdict`'s rule (higher is ahead)."""


def progress_line(plan: Plan, records: list[dict[str, Any]], reference: Learner) -> str:
    """Whether the learners were compared at matched progress (docs/meta-rl.md: at their
    plateau, or at equal adaptation gain): per benchmark and learner other than ``reference``,
    its adaptation gain on p0 minus the reference's, per seed on the same tasks, as mean ±
    standard error over seeds and the seeds where it is higher; *ahead* or *behind* by
    :func:`verdict`'s rule, else *level*. Where every learner is level, the comparison at equal
    iterations is also one at equal gain; where one is not, the line says that for it the
    comparison is at equal iterations only. Empty where no two seeds pair a gain."""
    benchmarks = _benchmarks(plan)
    findings: list[str] = []
    unmatched: dict[str, list[str]] = {}  # ahead / behind → the learners
    for benchmark in benchmarks:
        where = {"benchmark": benchmark, "distribution": INITIAL, "noisy": False}
        ours = [r for r in select(records, method=reference[0], variant=reference[1], **where)
                if r.get("gain") is not None]
        if not ours:
            continue
        theirs = {(r["seed"], r["task_seed"], r["n_tasks"]): r["gain"] for r in ours}
        places = decimals(over_seeds([r["mean"] for r in ours]).mean)  # as the gain table
        for learner in _learners(plan):
            if learner == reference:
                continue
            values = [r["gain"] - theirs[key] for r in select(
                records, method=learner[0], variant=learner[1], **where)
                if r.get("gain") is not None
                and (key := (r["seed"], r["task_seed"], r["n_tasks"])) in theirs]
            if len(values) < 2:
                continue
            spread = over_seeds(values)
            word = PROGRESS_WORDS[verdict(values, higher_better=True)]
            label = learner_label(plan, learner) + (
                f" on {display(benchmark)}" if len(benchmarks) > 1 else "")
            findings.append(f"{label} {spread.mean:+.{places}f} ± {spread.se:.{places}f} "
                            f"({sum(v > 0 for v in values)}/{len(values)} seeds higher), "
                            f"{word}")
            if word != PROGRESS_WORDS[NO_HELP]:
                unmatched.setdefault(word, []).append(label)
    if not findings:
        return ""
    reference_label = learner_label(plan, reference)
    if unmatched:
        sides = [" and ".join(names) + (" is " if len(names) == 1 else " are ") + word
                 for word, names in unmatched.items()]
        whom = "it" if sum(map(len, unmatched.values())) == 1 else "them"
        ending = (f"{'; '.join(sides)}, so for {whom} the comparison is at equal iterations, "
                  "not at equal gain.")
    else:
        ending = (f"Every learner's gain is level with {reference_label}'s within the spread, "
                  "so the learners compared at equal iterations are also compared at equal "
                  "gain.")
    return (f"- **Matched progress?** The adaptation gain on p0 at the compared iteration, "
            f"each learner's minus {reference_label}'s per seed on the same tasks (mean ± its "
            "standard error over seeds; *ahead* or *behind* by the rule, else *level*): "
            + "; ".join(findings) + ". " + ending)


def _count(n: int, noun: str) -> str:
    """``1 distribution``, ``3 distributions``."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _adaptation_caveat(plan: Plan, records: list[dict[str, Any]], learner: Learner) -> str:
    """`` It adapts on p0 at k of S seeds: …`` for a learner with a seed whose p0 gain is not
    beyond twice its standard error over tasks; empty otherwise."""
    caveats = []
    for benchmark in _benchmarks(plan):
        _, adapting, seeds = _gain(records, benchmark=benchmark, method=learner[0],
                                   variant=learner[1], distribution=INITIAL, noisy=False)
        if seeds and adapting < seeds:
            caveats.append(f"{adapting} of {seeds} seeds"
                           + (f" on {display(benchmark)}" if len(_benchmarks(plan)) > 1 else ""))
    if not caveats:
        return ""
    return (f" It adapts on p0 at {', '.join(caveats)} only: where it does not, the comparison "
            "is between policies, not meta-learners.")


ADVERSARY_NOTE = ("MPTS-MAML's and PDTS-MAML's training batches are drawn by a risk "
                  "predictor, not from a density over the box: they have no KL from p0 and no "
                  "mass to read, and are left out.")
"""Why the predictive samplers' batches have no row among the adversaries."""


def adversary_learners(plan: Plan) -> dict[str, tuple[Learner, bool]]:
    """Each adversary distribution of the experiment → the learner it was trained against and
    whether it is an attack: an AR adversary's co-trained learner (its method and variant),
    an attack's target (the finished learner it was trained against alone)."""
    found: dict[str, tuple[Learner, bool]] = {}
    for name, adversary in plan.spec.get("adversaries", {}).items():
        found[name] = ((adversary["method"], adversary.get("variant", "")), False)
    for name, attack in plan.spec.get("attacks", {}).items():
        found[name] = ((attack["target"], attack.get("variant", "")), True)
    return found


def worst_quarter_mass(records: list[dict[str, Any]], learner: Learner, distribution: str,
                       **where: Any) -> list[tuple[float, float | None]]:
    """Per seed, the mass ``distribution`` puts on the quarter of the box where ``learner``
    scores worst on p0 (its p0 section's ``quarter_scores``), beside p0's own mass there
    (``None`` if its section predates the masses); seeds without both are left out."""
    higher = _higher_better(records)
    initial = {r["seed"]: r for r in select(records, method=learner[0], variant=learner[1],
                                            distribution=INITIAL, **where)}
    found = []
    for record in select(records, method=learner[0], variant=learner[1],
                         distribution=distribution, **where):
        base = initial.get(record["seed"])
        scores = None if base is None else [base.get(f"quarter_scores_{q}") for q in range(4)]
        if scores is None or record.get("quarter_mass_0") is None:
            continue
        present = [(s, q) for q, s in enumerate(scores) if s is not None]
        if not present:
            continue
        worst = (min if higher else max)(present)[1]
        found.append((record[f"quarter_mass_{worst}"], base.get(f"quarter_mass_{worst}")))
    return found


def loss_ratios(records: list[dict[str, Any]], learner: Learner, distribution: str,
                **where: Any) -> dict[int, float]:
    """Seed → E_{p_φ}[loss] / E_{p0}[loss] of ``learner`` from its sections' means (for
    returns the loss is −return): how much harder the adversary made the tasks. Seeds whose
    mean loss on p0 is not positive are left out: the ratio of a loss that changes sign
    measures nothing."""
    sign = -1.0 if _higher_better(records) else 1.0
    initial = {r["seed"]: r["mean"] for r in select(records, method=learner[0],
                                                     variant=learner[1], distribution=INITIAL,
                                                     **where)}
    return {r["seed"]: (sign * r["mean"]) / (sign * initial[r["seed"]])
            for r in select(records, method=learner[0], variant=learner[1],
                            distribution=distribution, **where)
            if r["seed"] in initial and sign * initial[r["seed"]] > 0}


def kl_ratio(attack: Sequence[float],
             cotrained: Sequence[float]) -> tuple[float | None, float | None]:
    """mean(attack) / mean(co-trained) of per-seed KLs paired by seed, and its standard error
    over seeds by the delta method, std(z)/√n with z_s = (a_s − ratio·c_s) / mean(c); ``None``
    for the ratio where the co-trained mean is not positive (an adversary that did not move),
    for the error with one seed."""
    n = len(attack)
    mean_a, mean_c = sum(attack) / n, sum(cotrained) / n
    if not mean_c > 0:
        return None, None
    ratio = mean_a / mean_c
    if n < 2:
        return ratio, None
    z = [(a - ratio * c) / mean_c for a, c in zip(attack, cotrained)]
    return ratio, over_seeds(z).se


def _spread(values: Sequence[float], places: int = 2) -> str:
    if not values:
        return "–"
    spread = over_seeds(values)
    return (f"{spread.mean:.{places}f}" if spread.n < 2
            else f"{spread.mean:.{places}f} ± {spread.std:.{places}f}")


def adversary_section(plan: Plan, records: list[dict[str, Any]]) -> str:
    """Meta-RL: the strength of every adversary, a row per adversary distribution with the
    learner it was trained against (:func:`adversary_learners`): KL(p0 ‖ p_φ) (its non-negative
    estimate, mean ± std over seeds [root-mean-square Monte-Carlo standard error]), p_φ's mass
    on the quarter of the box where that learner does worst on p0
    (:func:`worst_quarter_mass`), and E_{p_φ}[loss] / E_{p0}[loss] (:func:`loss_ratios`).
    Empty without adversaries."""
    adversaries = adversary_learners(plan)
    if not adversaries:
        return ""
    labels = _distributions(plan)
    rows = []
    for benchmark in _benchmarks(plan):
        for name, (learner, attack) in adversaries.items():
            where = {"benchmark": benchmark, "noisy": False}
            masses = worst_quarter_mass(records, learner, name, **where)
            base = [b for _, b in masses if b is not None]
            mass = _spread([m for m, _ in masses])
            if masses and len(base) == len(masses):
                mass += f" (p0: {_spread(base)})"
            rows.append([display(benchmark), labels[name],
                         learner_label(plan, learner) + (" (attack)" if attack else ""),
                         _level(records, "kl_p0", "kl_p0_sem", method=learner[0],
                                variant=learner[1], distribution=name, **where),
                         mass,
                         _spread(list(loss_ratios(records, learner, name, **where).values()))])
    header = ["Benchmark", "Adversary", "trained against", "KL(p0 ‖ p_φ)",
              "mass on the learner's worst quarter", "E_{p_φ}[loss] / E_{p0}[loss]"]
    predictive = any(method.startswith(("mpts", "pdts")) for method, _ in _learners(plan))
    return ("**The adversaries' strength**, each read against the learner it was trained "
            "against (for a p_φ of another seed: the learner of its method at the evaluating "
            "seed): KL(p0 ‖ p_φ), mean ± std over seeds [root-mean-square of its Monte-Carlo "
            "standard error, recorded with the non-negative estimator; a cell without it comes "
            "from evaluations that took the plain Monte-Carlo mean of ln p0/p_φ]; p_φ's mass on "
            "the quarter of the box where that learner scores worst on p0 (quarters: four equal "
            "intervals of a 1-D box, the 2 × 2 cells of the halves of the first two identifiers "
            "otherwise), beside p0's mass there; E_{p_φ}[loss] / E_{p0}[loss] of that learner "
            "from the sections' means (for returns the loss is minus the return; undefined "
            "where the mean loss on p0 is not positive). – where the evaluations predate the "
            "field.\n\n"
            + markdown_table(header, rows)
            + (f"\n\n{ADVERSARY_NOTE}" if predictive else ""))


def attack_check(plan: Plan, records: list[dict[str, Any]], benchmark: str) -> list[str]:
    """A sentence per attack on ``benchmark``: whether the attack adversary (trained against a
    finished learner, nothing holding it but its step rule) moved clearly further from p0 than
    the co-trained adversary of its kind (the ``adversaries`` entry of the same method and
    variant at the same seed): the ratio of their KLs over the seeds both have
    (:func:`kl_ratio`) beyond 1 by more than twice its standard error (at one seed: no verdict
    yet). If so, the game, not the step, holds the co-trained adversary; if not, and the attacks
    take Adam steps, the step rule may. Then what each did to its own learner
    (:func:`strength_comparison`): where natural steps (no cap) took both equally far and the
    attack is clearly stronger, the learner's answer is what holds the co-trained adversary."""
    sentences = []
    adversaries = plan.spec.get("adversaries", {})
    labels = _distributions(plan)
    for name, attack in plan.spec.get("attacks", {}).items():
        kind = (attack["method"], attack.get("variant", ""))
        twin = next((other for other, spec in adversaries.items()
                     if (spec["method"], spec.get("variant", "")) == kind
                     and spec.get("seed_shift", 0) == 0), None)
        if twin is None:
            continue
        target = (attack["target"], attack.get("variant", ""))
        where = {"benchmark": benchmark, "noisy": False}
        attacked = {r["seed"]: r["kl_p0"] for r in select(
            records, method=target[0], variant=target[1], distribution=name, **where)
            if r.get("kl_p0") is not None}
        cotrained = {r["seed"]: r["kl_p0"] for r in select(
            records, method=kind[0], variant=kind[1], distribution=twin, **where)
            if r.get("kl_p0") is not None}
        seeds = sorted(attacked.keys() & cotrained.keys())
        if not seeds:
            continue
        a, c = [attacked[s] for s in seeds], [cotrained[s] for s in seeds]
        ratio, se = kl_ratio(a, c)
        lead = (f"On {display(benchmark)}, the attack" if len(_benchmarks(plan)) > 1
                else "The attack")
        compared = (f"**{lead} against {learner_label(plan, target)}** ({labels[name]}, KL "
                    f"{sum(a) / len(a):.2f}) against the co-trained adversary ({labels[twin]}, "
                    f"KL {sum(c) / len(c):.2f})")
        if ratio is None:
            sentences.append(f"{compared}: the co-trained adversary did not move from p0, so "
                             "there is no ratio.")
            continue
        if se is None:
            sentences.append(f"{compared}: KL ratio {ratio:.2f} at one seed: no standard error "
                             "over seeds, no verdict yet.")
            continue
        further = ratio - 1 > 2 * se
        natural = _natural_steps(plan, benchmark, target)
        capped = ("" if natural else
                  " Where both sit where the step rule stops against any loss (Adam at 0.5 / "
                  "iterations: near KL 0.3; docs/adversary.md), "
                  "the step rule, not the game, holds them.")
        strength, stronger = strength_comparison(
            loss_ratios(records, target, name, **where), loss_ratios(records, kind, twin, **where),
            learner_label(plan, target), learner_label(plan, kind))
        answered = (" Both went equally far from p0, natural steps capping neither, and the "
                    "co-trained adversary is clearly weaker against its learner than the attack "
                    "against a frozen one: the learner's answer, not the step rule, is what "
                    "holds it back." if natural and not further and stronger else "")
        sentences.append(
            f"{compared}: KL ratio {ratio:.2f} ± {se:.2f} (ratio of the means over "
            f"{len(seeds)} seeds, standard error over seeds). "
            + ("It moved clearly further (beyond 1 by more than twice its error): the game, "
               "not the step rule, holds the co-trained adversary." if further else
               "It did not move clearly further (not beyond 1 by twice its error): in KL, "
               "training against the learner held the co-trained adversary back no more than "
               "a frozen learner held the attack." + capped)
            + strength + answered)
    return sentences


STRENGTH_WORDS = {HELPS: "clearly stronger", HURTS: "clearly weaker",
                  NO_HELP: "not clearly stronger"}
"""The attack's strength against the co-trained adversary's by :func:`verdict`'s rule."""


def strength_comparison(attack: dict[int, float], cotrained: dict[int, float],
                        target: str, learner: str) -> tuple[str, bool]:
    """A sentence comparing how much harder each adversary made its own learner's tasks, seed →
    E_{p_φ}[loss] / E_{p0}[loss] (:func:`loss_ratios`) of the attack against ``target`` and of
    the co-trained adversary against ``learner``, paired by seed: the mean ratios, their
    difference ± its standard error over seeds and the seeds where the attack's is higher, and
    *clearly stronger* or *clearly weaker* by :func:`verdict`'s rule (else *not clearly
    stronger*); whether it is clearly stronger. KL measures how far an adversary moved, this
    what the move does to its learner: a co-trained adversary as far from p0 as the attack can
    be weaker against its learner, which adapts to it. Empty below two paired seeds."""
    seeds = sorted(attack.keys() & cotrained.keys())
    if len(seeds) < 2:
        return "", False
    differences = [attack[s] - cotrained[s] for s in seeds]
    spread = over_seeds(differences)
    places = decimals(spread.mean)
    word = verdict(differences, higher_better=True)
    return (f" By what it does to its learner, the attack raised {target}'s loss to "
            f"{over_seeds([attack[s] for s in seeds]).mean:.2f}× its loss on p0, the co-trained "
            f"adversary {learner}'s to {over_seeds([cotrained[s] for s in seeds]).mean:.2f}×: "
            f"difference {spread.mean:+.{places}f} ± {spread.se:.{places}f} "
            f"({sum(d > 0 for d in differences)}/{len(seeds)} seeds higher), "
            f"{STRENGTH_WORDS[word]}.", word == HELPS)


def _natural_steps(plan: Plan, benchmark: str, target: Learner) -> bool:
    """Whether the attack runs against ``target`` on ``benchmark`` take natural steps
    (``risk.ar.step=natural``: no step rule caps how far they move)."""
    return any(composed(run_command(run)).risk.ar.step == "natural" for run in plan.attacks
               if run.benchmark == benchmark and run.target is not None
               and (run.target.method, run.target.variant) == target)


TREND_WORDS = {HELPS: "rising", HURTS: "falling", NO_HELP: "level"}
"""A late change's direction by :func:`verdict`'s rule (taking a rise as the better side)."""


def late_trend(rows: Sequence[dict[str, Any]], labels: dict[str, str]) -> str:
    """The learning curves' late changes (:func:`~armeta_rl.reproduce.curves.late_changes`)
    per benchmark and run of ``labels`` (name → label): the training score (the return after
    adaptation, or the task loss where there is none), the adaptation gain and the adversary's
    KL from p0, each as its mean ± standard error over seeds, the seeds where it rose, and
    *rising* or *falling* by the docs' rule (beyond twice its error, the same way at 80 % of the
    seeds), else *level*: whether the learners were compared at their plateau or still
    improving, and whether an adversary still moved. A change takes the decimals of the level it
    is a change of (:func:`~armeta_rl.reproduce.curves.late_levels`). Empty when no run has two
    late parts."""
    returns = any(row["return_post"] is not None for row in rows)
    columns = ["return_post" if returns else "task_loss_mean", "gain", "adversary_kl_p0"]
    means = {column: late_means(rows, column) for column in columns}
    changes = {column: late_changes(means[column]) for column in columns}
    levels = {column: late_levels(means[column]) for column in columns}
    columns = [column for column in columns if changes[column]]
    keys = [(benchmark, name) for benchmark in dict.fromkeys(row["benchmark"] for row in rows)
            for name in labels if any((benchmark, name) in changes[c] for c in columns)]
    if not keys:
        return ""

    def cell(values: list[float] | None, level: float) -> str:
        if not values:
            return "–"
        spread = over_seeds(values)
        places = difference_decimals(level, spread.se if spread.n > 1 else math.nan)
        up = sum(v > 0 for v in values)
        if spread.n < 2:
            return f"{spread.mean:+.{places}f} (1 seed)"
        return (f"{spread.mean:+.{places}f} ± {spread.se:.{places}f} ({up}/{spread.n} up) "
                f"{TREND_WORDS[verdict(values, higher_better=True)]}")

    header = ["Benchmark", "Run", *(figures.CURVE_PANELS[column] for column in columns)]
    table = markdown_table(header, [
        [display(benchmark), labels[name], *(
            cell(changes[c].get((benchmark, name)), levels[c].get((benchmark, name), math.nan))
            for c in columns)]
        for benchmark, name in keys])
    ends: dict[tuple[str, str, int], int] = {}  # each run's and seed's last iteration
    for row in rows:
        run = (row["benchmark"], row["run"], row["seed"])
        ends[run] = max(ends.get(run, 0), row["iteration"])
    late, before = late_parts(Counter(ends.values()).most_common(1)[0][0])
    part = f"1/{LATE_PARTS}"
    return (f"**Still moving at the end?** Each run's mean over the last {part} of its "
            f"iterations minus its mean over the {part} before (for {late[-1]} iterations: "
            f"{late[0]}–{late[-1]} against {before[0]}–{before[-1]}), mean ± standard error "
            "over seeds (seeds where it rose / seeds): *rising* or *falling* where the change "
            "is beyond twice its error and goes the same way at 80 % of the seeds, else "
            "*level*. A learner still rising was compared before "
            "its plateau, an adversary still rising had not stopped moving (the attack check "
            "compares adversaries at equal iterations). Training scores are on each learner's "
            "own training tasks (AR-MAML's from its moving p_φ).\n\n" + table)


LAYOUTS: dict[str, Callable[[Plan, list[dict[str, Any]], Path], str]] = {
    "table": table,
    "cvar_curves": cvar_curves,
    "scatter": scatter,
    "noise": noise,
    "bars": bar_chart,
    "entropy": entropy,
    "paired": paired,
}
"""The experiment YAML's ``layout`` → the function writing its Markdown body and figures."""
