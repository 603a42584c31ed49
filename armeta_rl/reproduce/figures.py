"""PNG figures of an experiment (matplotlib, object API: no global pyplot state).

Error bars and bands are standard errors over seeds, as in the paper's figures.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from armeta_rl.plots import read_image
from armeta_rl.reproduce.aggregate import display, method_curve, select, summary
from armeta_rl.trainers.run_dir import write_atomically


def _save(figure: Figure, path: Path, dpi: int) -> None:
    """Save ``figure`` as the PNG ``path`` atomically (a kill leaves the old figure or none)."""
    write_atomically(path, lambda staged: figure.savefig(staged, dpi=dpi))


def _figure(rows: int, cols: int, width: float = 4.2, height: float = 3.4) -> Figure:
    figure = Figure(figsize=(width * cols, height * rows), layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def cvar_curves(records: Sequence[dict[str, Any]], benchmarks: Sequence[str],
                methods: Sequence[str], distributions: dict[str, str], path: Path) -> None:
    """CVaR_α against α per method (mean over seeds, standard-error band); one panel per
    benchmark (rows) and distribution (columns)."""
    figure = _figure(len(benchmarks), len(distributions))
    axes = figure.subplots(len(benchmarks), len(distributions), squeeze=False)
    for row, benchmark in enumerate(benchmarks):
        for col, (distribution, label) in enumerate(distributions.items()):
            ax = axes[row][col]
            for method in methods:
                curve = method_curve(records, benchmark, method, distribution)
                if curve is None:
                    continue
                alphas, points = curve
                mean = [p.mean for p in points]
                se = [0.0 if p.n < 2 else p.se for p in points]
                ax.plot(alphas, mean, marker="o", markersize=3, label=display(method))
                ax.fill_between(alphas, [m - s for m, s in zip(mean, se)],
                                [m + s for m, s in zip(mean, se)], alpha=0.2)
            ax.set_title(f"{display(benchmark)}: {label}", fontsize=9)
            ax.set_xlabel("α")
            ax.set_ylabel("CVaR_α")
    axes[0][0].legend(fontsize=7)
    _save(figure, path, 90)


def scatter(records: Sequence[dict[str, Any]], benchmarks: Sequence[str],
            methods: Sequence[str], adversaries: dict[str, str], path: Path) -> None:
    """Mean on p0 (x) against mean on an adversary (y), one point per method and seed, with the
    y = x line; one panel per benchmark (rows) and adversary (columns)."""
    figure = _figure(len(benchmarks), len(adversaries), 4.2, 4.0)
    axes = figure.subplots(len(benchmarks), len(adversaries), squeeze=False)
    for row, benchmark in enumerate(benchmarks):
        for col, (adversary, label) in enumerate(adversaries.items()):
            ax = axes[row][col]
            values = []
            for method in methods:
                x = {r["seed"]: r["mean"] for r in select(
                    records, benchmark=benchmark, method=method, distribution="initial",
                    noisy=False)}
                y = {r["seed"]: r["mean"] for r in select(
                    records, benchmark=benchmark, method=method, distribution=adversary,
                    noisy=False)}
                seeds = sorted(set(x) & set(y))
                ax.scatter([x[s] for s in seeds], [y[s] for s in seeds], label=display(method),
                           s=18)
                values += [x[s] for s in seeds] + [y[s] for s in seeds]
            if values:
                low, high = min(values), max(values)
                pad = 0.05 * (high - low or 1.0)
                ax.plot([low - pad, high + pad], [low - pad, high + pad], "k--", lw=0.8,
                        label="y = x")
            ax.set_title(f"{display(benchmark)}: {label}", fontsize=9)
            ax.set_xlabel("initial (p0)")
            ax.set_ylabel("adversarial")
    axes[0][0].legend(fontsize=7)
    _save(figure, path, 90)


def bars(records: Sequence[dict[str, Any]], benchmarks: Sequence[str], methods: Sequence[str],
         groups: Sequence[tuple[str, dict[str, Any], str]], path: Path, ylabel: str) -> None:
    """Grouped bar charts with standard-error bars, one panel per benchmark: one group per
    ``(label, record filter, column)`` (e.g. ("initial, average", {"distribution": "initial"},
    "mean")), one bar per method."""
    figure = _figure(len(benchmarks), 1, max(6.0, 1.6 * len(groups)), 3.6)
    axes = figure.subplots(len(benchmarks), 1, squeeze=False)[:, 0]
    width = 0.8 / len(methods)
    for ax, benchmark in zip(axes, benchmarks):
        for index, method in enumerate(methods):
            heights, errors, positions = [], [], []
            for position, (_, where, column) in enumerate(groups):
                value = summary(records, column, benchmark=benchmark, method=method, **where)
                if value is None:
                    continue
                heights.append(value.mean)
                errors.append(0.0 if value.n < 2 else value.se)
                positions.append(position + (index - (len(methods) - 1) / 2) * width)
            ax.bar(positions, heights, width, yerr=errors, capsize=3, label=display(method),
                   ecolor="black")
        ax.set_xticks(range(len(groups)), [label for label, _, _ in groups], fontsize=8)
        ax.set_ylabel(ylabel)
        ax.set_title(display(benchmark))
    axes[0].legend(fontsize=7)
    _save(figure, path, 90)


def lambda_curves(records: Sequence[dict[str, Any]], benchmarks: Sequence[str], method: str,
                  lambdas: dict[str, float], columns: dict[str, str], path: Path) -> None:
    """Mean and CVaR against λ on p0 and on the run's own adversary (mean over seeds, standard-
    error band); one panel per benchmark. ``lambdas``: variant → λ; ``columns``: key → label."""
    figure = _figure(1, len(benchmarks))
    axes = figure.subplots(1, len(benchmarks), squeeze=False)[0]
    order = sorted(lambdas, key=lambdas.get)
    for ax, benchmark in zip(axes, benchmarks):
        for distribution in ("initial", "same_seed"):
            for column, label in columns.items():
                points = [(lambdas[v], summary(records, column, benchmark=benchmark,
                                               method=method, variant=v,
                                               distribution=distribution, noisy=False))
                          for v in order]
                points = [(lam, s) for lam, s in points if s is not None]
                if not points:
                    continue
                xs = [lam for lam, _ in points]
                mean = [s.mean for _, s in points]
                se = [0.0 if s.n < 2 else s.se for _, s in points]
                name = "initial" if distribution == "initial" else "adversarial"
                ax.plot(xs, mean, marker="o", label=f"{label}, {name}")
                ax.fill_between(xs, [m - e for m, e in zip(mean, se)],
                                [m + e for m, e in zip(mean, se)], alpha=0.2)
        ax.set_title(f"{display(benchmark)}: {display(method)}", fontsize=9)
        ax.set_xlabel("λ")
        ax.legend(fontsize=7)
    _save(figure, path, 90)


def image_grid(images: dict[tuple[str, str], Path], rows: Sequence[str],
               cols: Sequence[str], path: Path) -> None:
    """The PNGs ``images[(row, col)]`` (e.g. the runs' density.png) in one figure."""
    figure = _figure(len(rows), len(cols), 5.5, 2.4)
    axes = figure.subplots(len(rows), len(cols), squeeze=False)
    for r, row in enumerate(rows):
        for c, col in enumerate(cols):
            ax = axes[r][c]
            ax.axis("off")
            if (row, col) in images:
                ax.imshow(read_image(images[(row, col)]))
                ax.set_title(f"{display(row)}, {col}", fontsize=8)
    _save(figure, path, 110)


CURVE_PANELS = {"gain": "adaptation gain", "return_post": "return after adaptation",
                "task_loss_mean": "task loss", "adversary_kl_p0": "adversary KL(p0 ‖ p_φ)",
                "task_spread": "training batch's spread (unit box)"}
"""The learning-curve panels: a curve file's column and its axis label."""


def learning_curves(rows: Sequence[dict[str, Any]], labels: dict[str, str], path: Path,
                    window: int = 10) -> None:
    """Training curves per iteration (:mod:`armeta_rl.reproduce.curves` rows): per benchmark
    (rows of panels), the adaptation gain, the return after adaptation (or the task loss where
    there is no return) and the adversary's KL from p0, each the mean over seeds of
    ``window``-iteration means with a band of ± one standard deviation over seeds, one line per
    run name in ``labels`` (name → legend)."""
    from armeta_rl.reproduce.aggregate import over_seeds
    from armeta_rl.reproduce.curves import windowed

    benchmarks = list(dict.fromkeys(r["benchmark"] for r in rows))
    panels = {b: [c for c in CURVE_PANELS
                  if any(r[c] is not None for r in rows if r["benchmark"] == b)
                  and not (c == "task_loss_mean" and any(
                      r["return_post"] is not None for r in rows if r["benchmark"] == b))]
              for b in benchmarks}
    columns = max(len(p) for p in panels.values())
    figure = _figure(len(benchmarks), columns)
    axes = figure.subplots(len(benchmarks), columns, squeeze=False)
    for row, benchmark in enumerate(benchmarks):
        for col, column in enumerate(panels[benchmark]):
            ax = axes[row][col]
            for index, (name, label) in enumerate(labels.items()):
                seeds: dict[int, list[tuple[int, float]]] = {}
                for r in rows:
                    if (r["benchmark"], r["run"]) == (benchmark, name) and r[column] is not None:
                        seeds.setdefault(r["seed"], []).append((r["iteration"], r[column]))
                if not seeds:
                    continue
                curves = [dict(windowed(sorted(v), window)) for v in seeds.values()]
                shared = sorted(set.intersection(*(set(c) for c in curves)))
                spread = [over_seeds([c[i] for c in curves]) for i in shared]
                mean = [s.mean for s in spread]
                std = [0.0 if s.n < 2 else s.std for s in spread]
                color = f"C{index % 10}"  # a run's colour is the same in every panel
                ax.plot(shared, mean, color=color, label=f"{label} ({len(curves)})")
                ax.fill_between(shared, [m - s for m, s in zip(mean, std)],
                                [m + s for m, s in zip(mean, std)], color=color, alpha=0.2)
            if column == "gain":
                ax.axhline(0.0, color="black", linewidth=0.6)
            ax.set_title(f"{display(benchmark)}: {CURVE_PANELS[column]}", fontsize=9)
            ax.set_xlabel("meta-iteration")
        drawn: dict[str, Any] = {}  # every run drawn in the row, once (an attack run has no gain)
        for ax in axes[row]:
            for handle, text in zip(*ax.get_legend_handles_labels(), strict=True):
                drawn.setdefault(text, handle)
        axes[row][0].legend(drawn.values(), drawn.keys(), fontsize=7)
    for row, benchmark in enumerate(benchmarks):
        for col in range(len(panels[benchmark]), columns):
            axes[row][col].set_visible(False)
    _save(figure, path, 90)
