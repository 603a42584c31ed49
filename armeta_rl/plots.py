"""Figures: the learned task distribution against p0 (paper figures "Task Structure Analysis"),
and its evolution during training as PNG frames and an animated GIF.

Figures are built on matplotlib's Agg canvas directly (no pyplot state, nothing to close), so they
work headless and from any thread.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import torch
from matplotlib.animation import PillowWriter
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LogNorm, Normalize
from matplotlib.figure import Figure
from matplotlib.image import imread
from torch import Tensor

from armeta_rl.errors import ConfigError
from armeta_rl.tasks.distributions import TaskDistribution

GRID_POINTS = 2**15
"""Most density evaluations one figure of a box of three or more identifiers makes."""
CHUNK = 2**16
"""Grid points per ``log_prob`` call (bounds the memory of the flow's inverse pass)."""


def density_on_grid(distribution: TaskDistribution, points_per_axis: int) -> Tensor:
    """exp(log_prob) at the midpoints of a regular grid over the box, shape ``[n] * d`` (axis k
    indexes identifier k), in float64 on the CPU; evaluated in chunks of :data:`CHUNK` points on the
    distribution's device."""
    grid, _ = distribution.space.grid(points_per_axis)
    grid = grid.to(distribution.low.device)
    with torch.no_grad():
        density = torch.cat([distribution.log_prob(part).exp() for part in grid.split(CHUNK)])
    return density.cpu().reshape([points_per_axis] * distribution.space.dim)


def pairwise_marginals(distribution: TaskDistribution,
                       points_per_axis: int) -> tuple[Tensor, Tensor, Tensor]:
    """The 1-D and 2-D marginal densities of ``distribution`` by midpoint quadrature over the
    other identifiers:

        p_i(τ_i) = ∫ p(τ) dτ_{-i},      p_ij(τ_i, τ_j) = ∫ p(τ) dτ_{-ij}

    Returns the grid midpoints ``[d, n]``, the 1-D marginals ``[d, n]`` and the 2-D marginals
    ``[d, d, n, n]`` (entry ``[i, j, a, b]`` at ``τ_i = axes[i, a], τ_j = axes[j, b]``; the
    diagonal ``i = j`` is left at zero). Each 1-D marginal integrates to one up to quadrature
    error (exactly one for any density constant on the grid cells)."""
    space = distribution.space
    low, high = space.bounds(torch.float64)
    width = (high - low) / points_per_axis
    axes = low[:, None] + width[:, None] * (torch.arange(points_per_axis) + 0.5)
    density = density_on_grid(distribution, points_per_axis)
    d = space.dim
    one = torch.stack([
        density.sum([k for k in range(d) if k != i]) * width[torch.arange(d) != i].prod()
        for i in range(d)
    ])
    two = torch.zeros(d, d, points_per_axis, points_per_axis, dtype=torch.float64)
    for i in range(d):
        for j in range(i + 1, d):
            others = [k for k in range(d) if k not in (i, j)]
            mask = (torch.arange(d) != i) & (torch.arange(d) != j)
            two[i, j] = density.sum(others) * width[mask].prod() if others else density
            two[j, i] = two[i, j].T
    return axes, one, two


def plot_density(distribution: TaskDistribution, initial: TaskDistribution, path: str | Path,
                 points_per_axis: int = 100, title: str | None = None) -> Figure:
    """Plot the density of ``distribution`` (e.g. p_φ) against ``initial`` (p0) and save a PNG.

    One identifier: both densities as curves on one axis. Two: two heat maps over the box on one
    logarithmic colour scale (so they compare, and a concentrated p_φ does not wash out p0), axes
    named by ``space.names``. Three or more: a grid of pairwise marginals
    (:func:`pairwise_marginals`): on the diagonal the 1-D marginals of both distributions as
    curves, below it the 2-D marginals of ``distribution`` as heat maps; the grid has at most
    :data:`GRID_POINTS` points, so ``points_per_axis`` shrinks as the dimension grows.

    Args:
        distribution: the distribution to show.
        initial: the reference distribution on the same box.
        path: where to write the PNG.
        points_per_axis: grid resolution.
        title: a title over the figure (e.g. the training iteration).

    Returns:
        The figure (already saved).
    """
    space = distribution.space
    if points_per_axis < 2:
        raise ConfigError("plots.points_per_axis", points_per_axis, "must be an integer >= 2")
    if space.dim == 1:
        figure = _curves(distribution, initial, points_per_axis)
    elif space.dim == 2:
        figure = _heat_maps(distribution, initial, points_per_axis)
    else:
        most = math.floor(GRID_POINTS ** (1 / space.dim) + 1e-9)
        figure = _marginals(distribution, initial, max(2, min(points_per_axis, most)))
    if title is not None:
        figure.suptitle(title)
    figure.savefig(path, dpi=100)
    return figure


def _drawable(top: float) -> bool:
    """Whether a colour scale can end at ``top``, the largest density on the grid: not where
    the density underflows to zero (or overflows) at every grid point, e.g. a distribution whose
    mass lies between the points; the map is then drawn blank on a unit scale."""
    return 0.0 < top < math.inf


def _new_figure(size: tuple[float, float]) -> Figure:
    figure = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _curves(distribution: TaskDistribution, initial: TaskDistribution, n: int) -> Figure:
    space = distribution.space
    grid, _ = space.grid(n)
    figure = _new_figure((6, 4))
    axis = figure.add_subplot()
    for shown, label in ((distribution, "adversarial p_φ"), (initial, "initial p0")):
        axis.plot(grid[:, 0].numpy(), density_on_grid(shown, n).numpy(), label=label)
    axis.set_xlabel(space.names[0])
    axis.set_ylabel("density")
    axis.legend()
    return figure


def _heat_maps(distribution: TaskDistribution, initial: TaskDistribution, n: int) -> Figure:
    space = distribution.space
    densities = [density_on_grid(shown, n).numpy() for shown in (distribution, initial)]
    extent = (space.low[0], space.high[0], space.low[1], space.high[1])
    top = max(float(density.max()) for density in densities)
    norm = LogNorm(vmin=top * 1e-4, vmax=top, clip=True) if _drawable(top) else Normalize(0, 1)
    figure = _new_figure((11, 4.5))
    axes = figure.subplots(1, 2)
    for axis, density, label in zip(axes, densities, ("adversarial p_φ", "initial p0"),
                                    strict=True):
        image = axis.imshow(density.T, origin="lower", extent=extent, aspect="auto",
                            cmap="viridis", norm=norm)
        axis.set_xlabel(space.names[0])
        axis.set_ylabel(space.names[1])
        axis.set_title(label)
    figure.colorbar(image, ax=axes, label="density")
    return figure


def _marginals(distribution: TaskDistribution, initial: TaskDistribution, n: int) -> Figure:
    space, d = distribution.space, distribution.space.dim
    axes_points, one, two = pairwise_marginals(distribution, n)
    _, one_initial, _ = pairwise_marginals(initial, n)
    top = float(two.max())
    norm = Normalize(vmin=0.0, vmax=top if _drawable(top) else 1.0)  # linear: smooth marginals
    figure = _new_figure((2.6 * d + 1, 2.4 * d))
    grid = figure.subplots(d, d, squeeze=False)
    for i in range(d):
        for j in range(d):
            axis = grid[i, j]
            if j > i:
                axis.set_axis_off()
                continue
            if i == j:
                axis.plot(axes_points[i].numpy(), one[i].numpy(), label="adversarial p_φ")
                axis.plot(axes_points[i].numpy(), one_initial[i].numpy(), label="initial p0")
                axis.set_ylabel("marginal density" if i == 0 else "")
            else:  # row i, column j < i: τ_j across, τ_i up
                extent = (space.low[j], space.high[j], space.low[i], space.high[i])
                image = axis.imshow(two[j, i].T.numpy(), origin="lower", extent=extent,
                                    aspect="auto", cmap="viridis", norm=norm)
                axis.set_ylabel(space.names[i] if j == 0 else "")
            axis.set_xlabel(space.names[j] if i == d - 1 else "")
    grid[0, 0].legend(loc="upper right", fontsize="small")
    figure.colorbar(image, ax=grid[1:, 0].tolist(), label="2-D marginal density of p_φ")
    return figure


def write_animation(frames: Sequence[str | Path], path: str | Path, fps: float = 2.0) -> None:
    """An animated GIF of the PNG ``frames`` (all of one size), in order, with matplotlib's
    ``PillowWriter``."""
    if not frames:
        raise ConfigError("plots.frames", [], "needs at least one PNG frame")
    first = imread(frames[0])
    height, width = first.shape[:2]
    dpi = 100
    figure = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    FigureCanvasAgg(figure)
    axis = figure.add_axes((0, 0, 1, 1))
    axis.set_axis_off()
    image = axis.imshow(first)
    writer = PillowWriter(fps=fps)
    with writer.saving(figure, str(path), dpi):
        for frame in frames:
            image.set_data(imread(frame))
            writer.grab_frame()
