"""``<experiment>.md`` and its figures, one layout per kind of artefact in the paper.

The experiment's YAML names its ``layout``; each layout writes the Markdown (our numbers, and the
paper's where its YAML holds them under ``paper``) and its PNGs into the results directory.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from armeta_rl.reproduce import figures
from armeta_rl.reproduce.aggregate import (
    INITIAL,
    SHIFT_PREFIX,
    SeedSummary,
    decimals,
    display,
    markdown_table,
    method_curve,
    over_seeds,
    select,
    summary,
)
from armeta_rl.reproduce.plan import Plan


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


def _difference(pairs: list[dict[str, Any]], column: str, higher_better: bool) -> str:
    """Paired differences over seeds: ``mean ± std [RMS task s.e.] (k/S better)``, in bold when
    the mean lies beyond twice its standard error over seeds."""
    if not pairs:
        return "–"
    values = [p[column] for p in pairs]
    spread = over_seeds(values)
    text = f"{spread.mean:+.{decimals(spread.mean)}f}"
    if spread.n > 1:
        text += f" ± {spread.std:.{decimals(spread.mean)}f}"
    sems = [p[f"{column}_sem" if column == "cvar" else "sem"] for p in pairs]
    sems = [s for s in sems if s is not None]
    if sems:
        text += f" [{(sum(s * s for s in sems) / len(sems)) ** 0.5:.{decimals(spread.mean)}f}]"
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
    return ("**Adaptation gain**: return after the inner step minus return before it, on the "
            "same episodes, mean ± std over seeds [root-mean-square over seeds of its "
            "standard error over tasks] (seeds whose gain is beyond twice that error / "
            "seeds).\n\n" + markdown_table(header, rows) + "\n\n" + verdict)


def paired(plan: Plan, records: list[dict[str, Any]], results: Path) -> str:
    """Meta-RL reports (docs/meta-rl.md): every learner's average and CVaR_α on p0, the
    adversaries and the shift suite (mean ± std over seeds [standard error over tasks]), then
    each learner minus the reference learner (``paired: {against: <method>}``) on the same tasks
    and random streams, per seed, summarized over seeds; figures of both."""
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
            diff_rows.append([display(benchmark), label, *(
                _difference(pairs[learner], column, higher)
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
    return ((adaptation + "\n\n" if adaptation else "")
            + markdown_table(level_header, level_rows)
            + f"\n\n![{plan.experiment}]({plan.experiment}.png)\n\nBars: mean over seeds, "
            "standard-error bars over seeds.\n\n"
            f"**Paired differences against {reference_label}**, on the same tasks and random "
            f"streams: each learner minus {reference_label} per seed ({better} is better for "
            f"the learner), mean ± std over seeds, [root-mean-square over seeds of the paired "
            f"standard error over tasks], (seeds where the learner is better / seeds). Bold: "
            "the mean is more than twice its standard error over seeds from 0.\n\n"
            + markdown_table(diff_header, diff_rows))


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
