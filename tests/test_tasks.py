"""Task space and initial distributions: exact, normalized densities on the box."""

import math

import pytest
import torch

from armeta_rl.errors import ConfigError
from armeta_rl.tasks import BoxUniform, TaskSpace, TruncatedNormal, make_initial

SINUSOID = TaskSpace(["amplitude", "phase"], [0.1, 0.0], [5.0, math.pi])


def test_space_rejects_empty_or_inverted_boxes():
    with pytest.raises(ConfigError, match="benchmark.space.low"):
        TaskSpace(["a", "b"], [0.0, 1.0], [1.0, 1.0])
    with pytest.raises(ConfigError, match="benchmark.space.high"):
        TaskSpace(["a", "b"], [0.0, 0.0], [1.0])


def test_unit_map_takes_the_box_onto_the_unit_cube():
    params = BoxUniform(SINUSOID).sample(64)["params"].double()
    unit = SINUSOID.to_unit(params)
    assert unit.min() >= 0 and unit.max() <= 1
    low, high = SINUSOID.bounds(torch.float64)
    corners = SINUSOID.to_unit(torch.stack([low, (low + high) / 2, high]))
    torch.testing.assert_close(corners, torch.tensor([[0.0, 0.0], [0.5, 0.5], [1.0, 1.0]],
                                                     dtype=torch.float64))


@pytest.mark.parametrize(
    "distribution",
    [BoxUniform(SINUSOID), TruncatedNormal(SINUSOID, [2.5, 1.5], [0.8, 0.5])],
    ids=["uniform", "truncated_normal"],
)
def test_density_integrates_to_one_and_samples_stay_in_box(distribution):
    grid, cell = SINUSOID.grid(300)
    assert float(distribution.log_prob(grid).exp().sum() * cell) == pytest.approx(1.0, abs=1e-3)
    tasks = distribution.sample(2000)
    assert SINUSOID.contains(tasks["params"]).all()
    torch.testing.assert_close(tasks["log_prob"], distribution.log_prob(tasks["params"]).float())
    outside = torch.tensor([[6.0, 1.0], [1.0, -0.1]])
    assert torch.isinf(distribution.log_prob(outside)).all()


def test_truncated_normal_samples_follow_the_density():
    distribution = TruncatedNormal(SINUSOID, [4.5, 0.3], [1.0, 0.5])
    grid, cell = SINUSOID.grid(300)
    weights = distribution.log_prob(grid).exp() * cell
    exact_mean = (weights[:, None] * grid).sum(0)
    torch.manual_seed(0)
    sample_mean = distribution.sample_params(200_000).mean(0)
    torch.testing.assert_close(sample_mean, exact_mean, atol=0.01, rtol=0)


def test_truncated_normal_is_normal_renormalized_on_the_box():
    loc, scale = torch.tensor([2.5, 1.5]), torch.tensor([0.8, 0.5])
    distribution = TruncatedNormal(SINUSOID, loc.tolist(), scale.tolist())
    normal = torch.distributions.Normal(loc.double(), scale.double())
    low, high = SINUSOID.bounds(torch.float64)
    mass = (normal.cdf(high) - normal.cdf(low)).prod()
    points = torch.tensor([[1.0, 0.5], [4.0, 2.5]], dtype=torch.float64)
    torch.testing.assert_close(
        distribution.log_prob(points), normal.log_prob(points).sum(-1) - mass.log()
    )


def test_uniform_entropy_is_log_volume():
    assert float(BoxUniform(SINUSOID).entropy()) == pytest.approx(math.log(4.9 * math.pi))
    assert float(BoxUniform(SINUSOID).entropy()) == pytest.approx(2.734, abs=1e-3)


def test_make_initial_names_the_bad_key():
    with pytest.raises(ConfigError, match="benchmark.initial.kind"):
        make_initial(SINUSOID, "beta")
    with pytest.raises(ConfigError, match="benchmark.initial.scale"):
        make_initial(SINUSOID, "normal", [1.0, 1.0], [0.5, -1.0])


def test_tasks_on_the_faces_round_into_the_box():
    # π rounds up in float32 (outside the box); 0.1 rounds up too (inside), 5.0 is exact
    space = TaskSpace(["a", "b"], [0.1, -math.pi], [5.0, math.pi])
    distribution = BoxUniform(space)
    params = torch.tensor([[0.1, math.pi], [5.0, -math.pi], [2.0, 1.0]], dtype=torch.float64)
    log_prob = distribution.log_prob(params)
    tasks = distribution.as_tasks(params, log_prob)
    cast = tasks["params"]
    assert cast.dtype == torch.get_default_dtype()
    assert space.contains(cast.double()).all()
    assert torch.isfinite(distribution.log_prob(cast)).all()
    plain = params.float()
    assert plain[0, 1].double() > math.pi and plain[1, 1].double() < -math.pi  # the hazard
    below_pi = torch.nextafter(plain[0, 1], torch.tensor(0.0))
    assert cast[0, 1] == below_pi and cast[1, 1] == -below_pi  # the nearest float32 inside
    inside = torch.tensor([[True, False], [True, False], [True, True]])
    assert torch.equal(cast[inside], plain[inside])  # everything else is the plain cast
    torch.testing.assert_close(tasks["log_prob"], log_prob.float())


def test_quarter_masses_sum_to_one_and_match_the_distributions_own():
    """A uniform p0 puts 1/4 on each quarter of a 1-D and of a 2-D box, a truncated normal
    its CDF's share of each of the four intervals, all within 4 standard errors of 4096 draws;
    the masses sum to 1."""
    torch.manual_seed(0)
    line = TaskSpace(["v"], low=[0.0], high=[2.0])
    square = TaskSpace(["x", "y"], low=[-1.0, 0.0], high=[1.0, 4.0])
    normal = TruncatedNormal(line, loc=[0.3], scale=[0.5])
    edges = torch.tensor([0.0, 0.5, 1.0, 1.5, 2.0], dtype=torch.float64)
    cdf = torch.special.ndtr((edges - 0.3) / 0.5)
    expected = {BoxUniform(line): [0.25] * 4, BoxUniform(square): [0.25] * 4,
                normal: ((cdf[1:] - cdf[:-1]) / (cdf[-1] - cdf[0])).tolist()}
    for distribution, shares in expected.items():
        mass = distribution.quarter_mass(4096)
        assert float(mass.sum()) == pytest.approx(1.0)
        for m, p in zip(mass.tolist(), shares):
            assert abs(m - p) < 4 * math.sqrt(p * (1 - p) / 4096)
