"""The adversary visible while it trains: p_φ drawn every N iterations into PNG frames
and an animated GIF, with exact marginals for boxes of three or more identifiers; colour scales
chosen from the densities' range, one per animation and one per pair of identifiers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from matplotlib.colors import LogNorm
from PIL import Image

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.config import validate
from armeta_rl.job import Job
from armeta_rl.plots import density_norm, pairwise_marginals, picture_norms, plot_density
from armeta_rl.tasks import BoxUniform, TaskSpace, TruncatedNormal
from armeta_rl.trainers.density import DensityFrames
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, compose_train, train_config

CUBE = TaskSpace(["m", "l", "g"], [0.4, 0.4, 5.0], [1.6, 1.6, 15.0])


def truncated_normal_1d(x: torch.Tensor, loc: float, scale: float, low: float,
                        high: float) -> torch.Tensor:
    """The density of N(loc, scale²) truncated to [low, high], written out."""
    cdf = torch.special.ndtr
    mass = cdf(torch.tensor((high - loc) / scale)) - cdf(torch.tensor((low - loc) / scale))
    return torch.exp(-0.5 * ((x - loc) / scale) ** 2) / (scale * math.sqrt(2 * math.pi) * mass)


def test_marginals_of_a_product_density_are_its_factors():
    loc, scale = [1.0, 0.8, 9.0], [0.3, 0.5, 2.0]
    distribution = TruncatedNormal(CUBE, loc, scale)
    axes, one, two = pairwise_marginals(distribution, 40)
    factors = torch.stack([truncated_normal_1d(axes[i], loc[i], scale[i], CUBE.low[i],
                                               CUBE.high[i]) for i in range(3)])
    # Midpoint quadrature of smooth factors: the other factors integrate to 1 - O(width²).
    torch.testing.assert_close(one, factors, rtol=2e-3, atol=0)
    torch.testing.assert_close(two[0, 2], factors[0][:, None] * factors[2][None], rtol=2e-3,
                               atol=0)
    torch.testing.assert_close(two[2, 0], two[0, 2].T)


def test_plotted_marginals_of_a_trained_looking_flow_integrate_to_one(tmp_path):
    torch.manual_seed(0)
    adversary = FlowAdversary(CUBE, BoxUniform(CUBE), "spline")
    with torch.no_grad():
        for parameter in adversary.parameters():
            parameter.add_(0.1 * torch.randn_like(parameter))
    figure = plot_density(adversary, adversary.base, tmp_path / "cube.png", points_per_axis=32)
    diagonal = [axis for axis in figure.axes if len(axis.lines) == 2]
    assert len(diagonal) == 3
    for axis, lo, hi in zip(diagonal, CUBE.low, CUBE.high, strict=True):
        x, density = (torch.as_tensor(a) for a in axis.lines[0].get_data())
        assert len(x) == 32
        # midpoint quadrature of a smooth density: one up to the quadrature error
        assert abs(float(density.sum()) * (hi - lo) / len(x) - 1.0) < 1e-2
        assert density.std() > 0  # the flow moved mass: not the uniform p0
    _, one, two = pairwise_marginals(adversary, 32)
    # Integrating a 2-D marginal over one identifier gives the other's 1-D marginal.
    torch.testing.assert_close(two[0, 1].sum(1) * (CUBE.high[1] - CUBE.low[1]) / 32, one[0])


@pytest.mark.parametrize(("benchmark", "iterations", "drawn"),
                         [("sinusoid_uniform", 5, (0, 2, 4, 5)), ("pendulum_gravity", 2, (0, 2))])
def test_a_short_run_writes_frames_and_an_animation(tmp_path, benchmark, iterations, drawn):
    """Frames at iteration 0 (p_φ = p0), every 2nd iteration and the last one (2-D heat maps for
    the sinusoid, pairwise marginals for the 3-D pendulum family)."""
    cfg = compose_train(*SMALL_RUN, f"benchmark={benchmark}", "trainer.meta_batch=4",
                        "trainer.density_every=2", f"trainer.iterations={iterations}",
                        "eval.n_tasks=4")
    run_training(Job(validate(cfg), tmp_path))
    frames = sorted(path.name for path in (tmp_path / "density").glob("*.png"))
    assert frames == [f"iter_{i:06d}.png" for i in drawn]
    assert all((tmp_path / "density" / f"iter_{i:06d}.pt").is_file() for i in drawn)
    with Image.open(tmp_path / "density.gif") as animation:
        assert animation.n_frames == len(drawn)
        with Image.open(tmp_path / "density" / frames[0]) as first:
            assert animation.size == first.size


def test_density_every_zero_draws_no_frames(tmp_path):
    run_training(Job(train_config(*SMALL_RUN, "trainer.density_every=0"), tmp_path))
    assert not (tmp_path / "density").exists() and not (tmp_path / "density.gif").exists()
    assert (tmp_path / "density.png").is_file()


def test_drawing_frames_leaves_the_seeded_run_unchanged(tmp_path):
    """Frames evaluate the exact density on a grid and draw no random numbers."""
    reports = [run_training(Job(train_config(*SMALL_RUN, f"trainer.density_every={every}"),
                                tmp_path / str(every))) for every in (0, 3)]
    assert (tmp_path / "3" / "density" / "iter_000006.png").is_file()
    assert reports[0] == reports[1]


def test_a_density_within_a_decade_of_p0_gets_a_linear_scale_beyond_it_a_log_scale_of_its_range():
    p0 = torch.ones(4, 4)
    linear = density_norm([torch.tensor([[0.2, 5.0], [3.0, 0.0]])], p0)
    assert not isinstance(linear, LogNorm) and (linear.vmin, linear.vmax) == (0.0, 5.0)
    two_decades = density_norm([torch.tensor([[0.5, 50.0], [3.0, 0.0]])], p0)
    assert isinstance(two_decades, LogNorm)
    assert (two_decades.vmin, two_decades.vmax) == (0.5, 50.0)  # its own range, not 4 decades
    sharp = density_norm([torch.tensor([[1e-9, 500.0], [3.0, 0.0]])], p0)
    assert (sharp.vmin, sharp.vmax) == pytest.approx((0.05, 500.0))  # at most 4 decades


def test_an_animation_keeps_p0_in_one_colour_while_p_phi_sharpens(tmp_path):
    """Frames drawn as p_φ concentrates are redrawn on one scale at the end: p0's heat map (the
    right half, below the title) is the same picture in every frame of the GIF."""
    space = TaskSpace(["a", "b"], [0.0, 0.0], [1.0, 1.0])
    torch.manual_seed(0)
    adversary = FlowAdversary(space, BoxUniform(space), "spline")
    frames = DensityFrames(adversary, adversary.base, tmp_path, every=1, points_per_axis=24)
    for iteration in range(3):
        frames.draw(iteration)
        with torch.no_grad():
            for parameter in adversary.parameters():
                parameter.add_(0.6 * torch.randn_like(parameter))
    frames.finish(2)
    pictures = []
    for iteration in range(3):
        with Image.open(frames.frame_path(iteration)) as image:
            pixels = np.asarray(image.convert("RGB"))
        pictures.append(pixels[60:, pixels.shape[1] // 2:])
    assert all(np.array_equal(pictures[0], other) for other in pictures[1:])
    with Image.open(tmp_path / "density.gif") as animation:
        assert animation.n_frames == 3


@pytest.mark.parametrize("names", [["a"], ["a", "b"]])
def test_finished_frames_are_their_numbers_on_the_common_scale_and_drawn_once_if_so(
        tmp_path, monkeypatch, names):
    """After :meth:`DensityFrames.finish` every frame is the drawing of its saved numbers on the
    scales of all frames; the frames already drawn on them (a curve has none; a heat map whose
    own scales are the common ones) are not drawn again."""
    import armeta_rl.trainers.density as density

    space = TaskSpace(names, [0.0] * len(names), [1.0] * len(names))
    torch.manual_seed(0)
    adversary = FlowAdversary(space, BoxUniform(space), "spline")
    frames = DensityFrames(adversary, adversary.base, tmp_path, every=1, points_per_axis=24)
    for iteration in range(3):
        if iteration == 2:
            with torch.no_grad():  # the last frame sharpens beyond the others: its scale is all's
                for parameter in adversary.parameters():
                    parameter.mul_(3.0)
        frames.draw(iteration)
    pictures = [DensityFrames._picture(frames.frame_path(i)) for i in range(3)]
    common = picture_norms(pictures)
    own = [density.same_scales(picture_norms([picture]), common) for picture in pictures]
    assert own == ([True] * 3 if len(names) == 1 else [False, False, True])
    drawn = []
    draw = density.draw_density
    monkeypatch.setattr(density, "draw_density", lambda *a, **k: drawn.append(a[2]) or draw(*a))
    frames.finish(2)
    assert drawn == [f"p_φ at meta-iteration {i}" for i in range(3) if not own[i]]
    for iteration, picture in enumerate(pictures):
        again = tmp_path / f"again_{iteration}.png"
        draw(picture, again, f"p_φ at meta-iteration {iteration}", common, space.low, space.high)
        assert frames.frame_path(iteration).read_bytes() == again.read_bytes()


def test_each_pair_of_identifiers_gets_its_own_colour_scale(tmp_path):
    """A density sharp in one identifier: the pairs with it peak far above the other pair, and
    each pair's heat map spans its own range."""
    sharp = TruncatedNormal(CUBE, [1.0, 1.0, 10.0], [0.02, 0.4, 3.0])
    figure = plot_density(sharp, BoxUniform(CUBE), tmp_path / "pairs.png", points_per_axis=30)
    tops = sorted(image.get_clim()[1] for axis in figure.axes for image in axis.images)
    assert len(tops) == 3 and tops[-1] > 5 * tops[0]



def figure_script():
    """docs/figures/density.py as a module."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "docs" / "figures" / "density.py"
    spec = importlib.util.spec_from_file_location("density_figure", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


def test_the_readme_figure_script_draws_a_finished_run_and_refuses_another(tmp_path):
    """docs/figures/density.py draws the final p_φ of the default run; a run of other settings
    is refused with one line (exit code 2), and draws when asked to take any run, keeping the
    numbers it drew and the machine that computed them."""
    import json

    script = figure_script()
    run = tmp_path / "run"
    run_training(Job(train_config(*SMALL_RUN, "trainer.meta_batch=4", "eval.n_tasks=4"), run))
    assert script.main(["--run", str(run), "--out", str(tmp_path / "refused.png")]) == 2
    assert not (tmp_path / "refused.png").exists()
    numbers, provenance = tmp_path / "numbers.pt", tmp_path / "provenance.json"
    out = script.draw(run, tmp_path / "figure.png", check_default=False, numbers=numbers,
                      provenance=provenance)
    with Image.open(out) as image:
        assert image.size[0] > image.size[1] > 100
    about = json.loads(provenance.read_text())
    assert about["machine"] == script.this_machine() and "armeta-train" in about["command"]
    redrawn = script.redraw(tmp_path / "redrawn.png", numbers, provenance)
    with Image.open(out) as first, Image.open(redrawn) as second:
        assert np.array_equal(np.asarray(first), np.asarray(second))


def test_the_readme_figure_is_redrawn_from_its_committed_numbers(tmp_path):
    """The README's figure is what its committed numbers draw (docs/figures/density.pt and
    density.json: the command and machine that computed them, named in its title)."""
    script = figure_script()
    redrawn = script.redraw(tmp_path / "density.png")
    with Image.open(script.FIGURE) as committed, Image.open(redrawn) as again:
        committed, again = np.asarray(committed, float), np.asarray(again, float)
    assert committed.shape == again.shape
    # matplotlib's wheels bring their own FreeType, so a redraw is the committed figure; a few
    # anti-aliased glyph pixels may differ on another machine, not a patch of a heat map (a
    # 0.4 % patch changed is 4 times this bound)
    differing = np.any(committed != again, axis=-1)
    assert differing.mean() < 1e-3
