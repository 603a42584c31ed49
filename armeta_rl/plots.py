"""Figures: the learned task distribution against p0 (paper figures "Task Structure Analysis"),
its evolution during training as PNG frames and an animated GIF, and a learner's adaptation
curve from its evaluation reports (:func:`plot_adaptation_curves`).

A figure is drawn from its numbers (:class:`DensityPicture`), so that an animation's frames can be
redrawn on one colour scale at the end. Scales follow the densities' range
(:func:`density_norm`): linear while p_φ stays within a decade of p0, logarithmic over its own
range beyond; each pair of identifiers of a pairwise-marginal grid has its own.

Figures are built on matplotlib's Agg canvas directly (no pyplot state, nothing to close), so they
work headless and from any thread.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from matplotlib.animation import PillowWriter
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LogNorm, Normalize
from matplotlib.figure import Figure
from matplotlib.image import imread
from torch import Tensor

from armeta_rl.errors import ConfigError
from armeta_rl.run_files import read_file
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
        density.sum(others) * width[torch.arange(d) != i].prod() if others else density
        for i in range(d)
        for others in [[k for k in range(d) if k != i]]
    ])
    two = torch.zeros(d, d, points_per_axis, points_per_axis, dtype=torch.float64)
    for i in range(d):
        for j in range(i + 1, d):
            others = [k for k in range(d) if k not in (i, j)]
            mask = (torch.arange(d) != i) & (torch.arange(d) != j)
            two[i, j] = density.sum(others) * width[mask].prod() if others else density
            two[j, i] = two[i, j].T
    return axes, one, two


@dataclass(frozen=True)
class DensityPicture:
    """What a density figure shows, as numbers: the grid midpoints ``axes`` ``[d, n]`` and, for
    the distribution and p0, the 1-D marginals ``[d, n]`` and the 2-D marginals ``[d, d, n, n]``
    (:func:`pairwise_marginals`; with two identifiers, the pair's marginal is the density
    itself). Saved beside each animation frame, so that the animation is drawn at the end on one
    colour scale."""

    names: tuple[str, ...]
    axes: Tensor
    one: Tensor
    two: Tensor
    one_initial: Tensor
    two_initial: Tensor

    @property
    def dim(self) -> int:
        return len(self.names)

    def pairs(self) -> list[tuple[int, int]]:
        """The identifier pairs drawn as heat maps, ``(j, i)`` with ``τ_j`` across, ``τ_i`` up:
        the one pair of a 2-D box, the pairs below the diagonal of a larger one."""
        return [(j, i) for i in range(self.dim) for j in range(i)]

    def state_dict(self) -> dict[str, Any]:
        return {"names": list(self.names), **{k: getattr(self, k) for k in TENSORS}}

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> DensityPicture:
        return cls(tuple(state["names"]), *(state[k] for k in TENSORS))


TENSORS = ("axes", "one", "two", "one_initial", "two_initial")


def density_picture(distribution: TaskDistribution, initial: TaskDistribution,
                    points_per_axis: int = 100) -> DensityPicture:
    """The numbers :func:`draw_density` draws: ``distribution`` (e.g. p_φ) and ``initial`` (p0)
    on a grid of ``points_per_axis`` per identifier (fewer for three identifiers or more, so that
    the grid has at most :data:`GRID_POINTS` points)."""
    space = distribution.space
    if points_per_axis < 2:
        raise ConfigError("plots.points_per_axis", points_per_axis, "must be an integer >= 2")
    if space.dim > 2:
        points_per_axis = max(2, min(points_per_axis,
                                     math.floor(GRID_POINTS ** (1 / space.dim) + 1e-9)))
    axes, one, two = pairwise_marginals(distribution, points_per_axis)
    _, one_initial, two_initial = pairwise_marginals(initial, points_per_axis)
    return DensityPicture(tuple(space.names), axes, one, two, one_initial, two_initial)


def density_norm(shown: Sequence[Tensor], reference: Tensor) -> Normalize:
    """The colour scale of heat maps of the densities ``shown`` (one figure's, or every frame's
    of an animation) beside ``reference``, p0's on the same cells.

    Linear from zero while every value stays within a decade of p0's largest: a density that
    moved mass within that range reads as its own shape, which a logarithmic scale flattens.
    Otherwise logarithmic over the values' own range: from the smallest positive value (at most
    four decades below the largest) to the largest, so a density spanning two decades gets two,
    not a fixed four in which it looks like p0."""
    values = torch.cat([v.reshape(-1) for v in (*shown, reference)])
    top = float(values.max())
    if not 0.0 < top < math.inf:  # the density underflows at every grid point: drawn blank
        return Normalize(vmin=0.0, vmax=1.0)
    if top <= 10 * float(reference.max()):
        return Normalize(vmin=0.0, vmax=top)
    smallest = float(values[values > 0].min())
    return LogNorm(vmin=max(smallest, top * 1e-4), vmax=top, clip=True)


def picture_norms(pictures: Sequence[DensityPicture]) -> dict[tuple[int, int], Normalize]:
    """One colour scale per drawn pair for all ``pictures`` (the frames of one animation, or one
    figure): :func:`density_norm` of the pair's 2-D marginals of every picture against p0's."""
    first = pictures[0]
    return {(j, i): density_norm([picture.two[j, i] for picture in pictures],
                                 first.two_initial[j, i])
            for j, i in first.pairs()}


def draw_density(picture: DensityPicture, path: str | Path, title: str | None = None,
                 norms: dict[tuple[int, int], Normalize] | None = None,
                 low: Sequence[float] = (), high: Sequence[float] = ()) -> Figure:
    """Draw ``picture`` and save a PNG at ``path``.

    One identifier: both densities as curves. Two: heat maps of p_φ and p0 side by side on one
    colour scale. Three or more: a grid of pairwise marginals, the 1-D marginals of both on the
    diagonal, the 2-D marginals of p_φ below it, each pair on its own colour scale. ``norms``
    gives the scale of each pair (:func:`picture_norms`; default: this picture's own); ``low``
    and ``high`` the box, for the heat maps' extent (default: the grid's)."""
    if picture.dim == 1:
        figure = _curves(picture)
    else:
        norms = picture_norms([picture]) if norms is None else norms
        half = (picture.axes[:, 1] - picture.axes[:, 0]) / 2
        low = list(low) or (picture.axes[:, 0] - half).tolist()
        high = list(high) or (picture.axes[:, -1] + half).tolist()
        figure = (_heat_maps(picture, norms, low, high) if picture.dim == 2
                  else _marginals(picture, norms, low, high))
    if title is not None:
        figure.suptitle(title)
    figure.savefig(path, dpi=100)
    return figure


def plot_density(distribution: TaskDistribution, initial: TaskDistribution, path: str | Path,
                 points_per_axis: int = 100, title: str | None = None) -> Figure:
    """Plot the density of ``distribution`` (e.g. p_φ) against ``initial`` (p0) and save a PNG
    (:func:`density_picture`, then :func:`draw_density` on the picture's own scales).

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
    return draw_density(density_picture(distribution, initial, points_per_axis), path, title,
                        low=space.low, high=space.high)


def plot_adaptation_curves(reports: Mapping[str, Mapping[str, Any]], path: str | Path,
                           section: str = "initial", title: str | None = None) -> Figure:
    """Plot the adaptation curves of evaluation reports (``eval.json``, ``eval_vs_<run>.json``):
    each report's score on distribution ``section`` after 0, 1, ..., k inner steps, with one
    standard error over tasks as a band, one line per report (its key the legend), saved as a
    PNG at ``path``.

    Raises:
        ConfigError: a report without an adaptation curve for ``section`` (not a meta-RL
            learner's, or written before reports had one).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from armeta_rl.plots import plot_adaptation_curves
        >>> report = {"metric": "return", "initial": {"adaptation_curve": {
        ...     "inner_steps": [0, 1, 2], "mean": [-30.0, -21.0, -19.5], "sem": [1.0, 0.9, 0.9]}}}
        >>> path = Path(tempfile.mkdtemp()) / "curve.png"
        >>> axis = plot_adaptation_curves({"MAML": report}, path).axes[0]
        >>> axis.get_ylabel(), axis.get_legend().get_texts()[0].get_text()
        ('return on initial (mean ± sem over tasks)', 'MAML')
        >>> band = axis.collections[0].get_paths()[0].get_extents()  # mean ± sem
        >>> round(float(band.y0), 2), round(float(band.y1), 2)  # -30 - 1 and -19.5 + 0.9
        (-31.0, -18.6)
    """
    figure = _new_figure((6, 4))
    axis = figure.add_subplot()
    metric = None
    for label, report in reports.items():
        curve = (report.get(section) or {}).get("adaptation_curve")
        if curve is None:
            raise ConfigError("report", label, f"has no adaptation curve for '{section}': "
                              "a meta-RL learner's evaluation report has one")
        metric = report.get("metric")
        mean = torch.tensor(curve["mean"], dtype=torch.float64)
        sem = torch.tensor([0.0 if e is None else e for e in curve["sem"]], dtype=torch.float64)
        axis.plot(curve["inner_steps"], mean, marker="o", label=label)
        axis.fill_between(curve["inner_steps"], mean - sem, mean + sem, alpha=0.2)
    axis.set_xlabel("inner steps")
    axis.set_ylabel(f"{metric} on {section} (mean ± sem over tasks)")
    axis.xaxis.get_major_locator().set_params(integer=True)
    axis.legend()
    if title:
        axis.set_title(title)
    figure.savefig(path, dpi=100)
    return figure


def _new_figure(size: tuple[float, float]) -> Figure:
    figure = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _curves(picture: DensityPicture) -> Figure:
    figure = _new_figure((6, 4))
    axis = figure.add_subplot()
    for density, label in ((picture.one[0], "adversarial p_φ"),
                           (picture.one_initial[0], "initial p0")):
        axis.plot(picture.axes[0].numpy(), density.numpy(), label=label)
    axis.set_xlabel(picture.names[0])
    axis.set_ylabel("density")
    axis.legend()
    return figure


def _heat_maps(picture: DensityPicture, norms: dict[tuple[int, int], Normalize],
               low: Sequence[float], high: Sequence[float]) -> Figure:
    extent = (low[0], high[0], low[1], high[1])
    figure = _new_figure((11, 4.5))
    axes = figure.subplots(1, 2)
    for axis, density, label in zip(axes, (picture.two[0, 1], picture.two_initial[0, 1]),
                                    ("adversarial p_φ", "initial p0"), strict=True):
        image = axis.imshow(density.T.numpy(), origin="lower", extent=extent, aspect="auto",
                            cmap="viridis", norm=norms[0, 1])
        axis.set_xlabel(picture.names[0])
        axis.set_ylabel(picture.names[1])
        axis.set_title(label)
    figure.colorbar(image, ax=axes, label="density")
    return figure


def _marginals(picture: DensityPicture, norms: dict[tuple[int, int], Normalize],
               low: Sequence[float], high: Sequence[float]) -> Figure:
    d, points = picture.dim, picture.axes
    figure = _new_figure((3.0 * d + 1, 2.4 * d))
    grid = figure.subplots(d, d, squeeze=False)
    for i in range(d):
        for j in range(d):
            axis = grid[i, j]
            if j > i:
                axis.set_axis_off()
                continue
            if i == j:
                axis.plot(points[i].numpy(), picture.one[i].numpy(), label="adversarial p_φ")
                axis.plot(points[i].numpy(), picture.one_initial[i].numpy(), label="initial p0")
                axis.set_ylabel("marginal density" if i == 0 else "")
            else:  # row i, column j < i: τ_j across, τ_i up, on the pair's own scale
                extent = (low[j], high[j], low[i], high[i])
                image = axis.imshow(picture.two[j, i].T.numpy(), origin="lower", extent=extent,
                                    aspect="auto", cmap="viridis", norm=norms[j, i])
                figure.colorbar(image, ax=axis, label="2-D marginal")
                axis.set_ylabel(picture.names[i] if j == 0 else "")
            axis.set_xlabel(picture.names[j] if i == d - 1 else "")
    grid[0, 0].legend(loc="upper right", fontsize="small")
    return figure


IMAGE_BYTES = 2**26
"""The most a PNG of a run (a density frame or figure, a few hundred KiB) is read."""


def read_image(path: str | Path, below: str | Path | None = None) -> Any:
    """The pixels of the PNG ``path``, read as every file of a run or results directory is
    (:func:`~armeta_rl.run_files.read_file`: a regular file of one link, at most
    :data:`IMAGE_BYTES`, reached from ``below`` through no link).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        FileRefused: it is not such a file.
        OSError, SyntaxError, ValueError: its bytes are not a PNG.
    """
    return imread(io.BytesIO(read_file(path, IMAGE_BYTES, below)), format="png")


def write_animation(frames: Sequence[str | Path], path: str | Path, fps: float = 2.0) -> None:
    """An animated GIF of the PNG ``frames`` (all of one size, read by :func:`read_image`), in
    order, with matplotlib's ``PillowWriter``."""
    if not frames:
        raise ConfigError("plots.frames", [], "needs at least one PNG frame")
    first = read_image(frames[0])
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
            image.set_data(read_image(frame))
            writer.grab_frame()
