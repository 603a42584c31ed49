"""Figures: the learned task distribution against p0 (paper figures "Task Structure Analysis").

Figures are built on matplotlib's Agg canvas directly (no pyplot state, nothing to close), so they
work headless and from any thread.
"""

from __future__ import annotations

from pathlib import Path

import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from armeta_rl.errors import ConfigError
from armeta_rl.tasks.distributions import TaskDistribution


def plot_density(distribution: TaskDistribution, initial: TaskDistribution, path: str | Path,
                 points_per_axis: int = 100) -> Figure:
    """Plot exp(log_prob) of ``distribution`` (e.g. p_φ) next to ``initial`` (p0) and save a PNG.

    For two identifiers: two heat maps over the box on one logarithmic colour scale (so they
    compare, and a concentrated p_φ does not wash out p0), axes named by ``space.names``. For one
    identifier: both densities as curves on one axis. More identifiers have no exact picture
    without integrating the density out, so they raise ``ConfigError``.

    Args:
        distribution: the distribution to show.
        initial: the reference distribution on the same box.
        path: where to write the PNG.
        points_per_axis: grid resolution.

    Returns:
        The figure (already saved).
    """
    space = distribution.space
    if space.dim not in (1, 2):
        raise ConfigError("benchmark.space.names", list(space.names),
                          "density plots need 1 or 2 task identifiers")
    if points_per_axis < 2:
        raise ConfigError("plots.points_per_axis", points_per_axis, "must be an integer >= 2")
    grid, _ = space.grid(points_per_axis)
    with torch.no_grad():
        densities = [d.log_prob(grid).exp().reshape([points_per_axis] * space.dim).numpy()
                     for d in (distribution, initial)]
    titles = ("adversarial p_φ", "initial p0")
    figure = Figure(figsize=(11, 4.5) if space.dim == 2 else (6, 4), layout="constrained")
    FigureCanvasAgg(figure)
    if space.dim == 1:
        axis = figure.add_subplot()
        for density, title in zip(densities, titles, strict=True):
            axis.plot(grid[:, 0].numpy(), density, label=title)
        axis.set_xlabel(space.names[0])
        axis.set_ylabel("density")
        axis.legend()
    else:
        extent = (space.low[0], space.high[0], space.low[1], space.high[1])
        top = max(float(density.max()) for density in densities)
        norm = LogNorm(vmin=top * 1e-4, vmax=top, clip=True)
        axes = figure.subplots(1, 2)
        for axis, density, title in zip(axes, densities, titles, strict=True):
            image = axis.imshow(density.T, origin="lower", extent=extent, aspect="auto",
                                cmap="viridis", norm=norm)
            axis.set_xlabel(space.names[0])
            axis.set_ylabel(space.names[1])
            axis.set_title(title)
        figure.colorbar(image, ax=axes, label="density")
    figure.savefig(path, dpi=120)
    return figure
