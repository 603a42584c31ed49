"""The adversary visible while it trains (issue 26): p_φ drawn every N iterations into PNG frames
and an animated GIF, with exact marginals for boxes of three or more identifiers."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import SMALL_RUN, compose_train
from PIL import Image

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.plots import pairwise_marginals, plot_density
from armeta_rl.tasks import BoxUniform, TaskSpace, TruncatedNormal
from armeta_rl.trainers.training import run_training

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
    run_training(cfg, tmp_path)
    frames = sorted(path.name for path in (tmp_path / "density").iterdir())
    assert frames == [f"iter_{i:06d}.png" for i in drawn]
    with Image.open(tmp_path / "density.gif") as animation:
        assert animation.n_frames == len(drawn)
        with Image.open(tmp_path / "density" / frames[0]) as first:
            assert animation.size == first.size


def test_density_every_zero_draws_no_frames(tmp_path):
    run_training(compose_train(*SMALL_RUN, "trainer.density_every=0"), tmp_path)
    assert not (tmp_path / "density").exists() and not (tmp_path / "density.gif").exists()
    assert (tmp_path / "density.png").is_file()


def test_drawing_frames_leaves_the_seeded_run_unchanged(tmp_path):
    """Frames evaluate the exact density on a grid and draw no random numbers."""
    reports = [run_training(compose_train(*SMALL_RUN, f"trainer.density_every={every}"),
                            tmp_path / str(every)) for every in (0, 3)]
    assert (tmp_path / "3" / "density" / "iter_000006.png").is_file()
    assert reports[0] == reports[1]
