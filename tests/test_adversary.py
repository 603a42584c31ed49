"""The adversary's contract (docs/architecture.md) for both flows, the follower's surrogate and
step, the ERM principle and the density plot."""

from __future__ import annotations

import copy
import io
import math

import numpy as np
import pytest
import torch

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.adversary.objective import adversary_surrogate, fisher_vector_product
from armeta_rl.errors import ConfigError, TrainingDiverged
from armeta_rl.plots import plot_density
from armeta_rl.risk.adversarial import AdversarialPrinciple, ArOptions
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.risk.erm import ERMPrinciple
from armeta_rl.rl.trpo import flatten
from armeta_rl.tasks import BoxUniform, TaskSpace, TruncatedNormal
from armeta_rl.tasks.distributions import kl_estimate

SINUSOID = TaskSpace(["amplitude", "phase"], [0.1, 0.0], [5.0, math.pi])
FLOWS = ["spline", "planar", "planar_leaky"]
"""Flow configurations: the spline flow, the tanh planar flow, and the paper's leaky-ReLU planar
flow (whose score-function gradient is biased, so contract 4 is not claimed for it)."""
FLOW_OPTIONS = {"spline": ("spline", {}), "planar": ("planar", {}),
                "planar_leaky": ("planar", {"activation": "leaky_relu"})}
BASES = ["uniform", "normal"]
GRID = 150
CORNER = torch.tensor([0.1, 0.0], dtype=torch.float64)


def make_base(kind: str, space: TaskSpace = SINUSOID):
    if kind == "uniform":
        return BoxUniform(space)
    low, high = space.bounds(torch.float64)
    return TruncatedNormal(space, ((low + high) / 2).tolist(), ((high - low) / 4).tolist())


def make_adversary(flow: str, base: str = "uniform", perturb: float = 0.0, seed: int = 0,
                   space: TaskSpace = SINUSOID) -> FlowAdversary:
    """An adversary; with ``perturb > 0`` every parameter gets N(0, perturb²) noise (away from
    the identity initialization)."""
    torch.manual_seed(seed)
    kind, options = FLOW_OPTIONS[flow]
    adversary = FlowAdversary(space, make_base(base, space), kind, **options)
    with torch.no_grad():
        for parameter in adversary.parameters():
            parameter.add_(perturb * torch.randn_like(parameter))
    return adversary


PERTURB = {"spline": 0.1, "planar": 0.3, "planar_leaky": 0.3}


def toy_loss(params: torch.Tensor) -> torch.Tensor:
    """L(τ) = ‖τ − c‖², high far from the corner c."""
    return (params.to(torch.float64) - CORNER).pow(2).sum(-1)


def grid_objective(adversary: FlowAdversary, lam: float,
                   points_per_axis: int = 100) -> torch.Tensor:
    """J(φ) = ∫ p_φ L + λ ∫ p0 ln p_φ by midpoint quadrature, the first term after the change of
    variables τ = g(τ0): ∫ p0(τ0) L(g(τ0)) dτ0 (a smooth integrand even where p_φ is peaked)."""
    grid, cell = adversary.space.grid(points_per_axis)
    p0 = adversary.base.log_prob(grid).exp()
    return cell * (p0 * toy_loss(adversary.flow(grid)[0])).sum() + lam * cell * (
        p0 * adversary.log_prob(grid)).sum()


# --- contract 1: samples always lie inside the box -----------------------------------------------

@pytest.mark.parametrize("flow", FLOWS)
@pytest.mark.parametrize("base", BASES)
def test_samples_stay_inside_the_box(flow: str, base: str) -> None:
    adversary = make_adversary(flow, base, perturb=3 * PERTURB[flow])
    params, log_prob = adversary.sample_with_log_prob(20_000)
    assert SINUSOID.contains(params).all()
    assert torch.isfinite(log_prob).all()
    tasks = adversary.sample(20_000)  # default dtype: π is not a float32 number
    assert tasks["params"].dtype == torch.get_default_dtype()
    assert SINUSOID.contains(tasks["params"].to(torch.float64)).all()


@pytest.mark.parametrize("flow", ["planar", "planar_leaky"])
def test_saturated_planar_samples_on_the_faces_stay_inside(flow: str) -> None:
    adversary = make_adversary(flow)
    with torch.no_grad():  # a large shift orthogonal to w pushes mass onto the faces
        layer = adversary.flow.layers[1]
        w1, w2 = layer.w[0]
        layer.u.copy_(60.0 * torch.stack([-w2, w1])[None] / layer.w.norm())
    params = adversary.sample(5_000)["params"].to(torch.float64)
    low, high = SINUSOID.bounds(torch.float64)
    on_face = ((params <= low + 1e-6) | (params >= high - 1e-6)).any(-1)
    assert on_face.float().mean() > 0.1
    assert SINUSOID.contains(params).all()
    assert torch.isfinite(adversary.log_prob(params)).all()


# --- contract 2: exact normalized density, evaluable anywhere ------------------------------------

@pytest.mark.parametrize("flow", FLOWS)
@pytest.mark.parametrize("base", BASES)
@pytest.mark.parametrize("perturbed", [False, True])
def test_log_prob_is_a_normalized_density_matching_sampling(flow: str, base: str,
                                                           perturbed: bool) -> None:
    adversary = make_adversary(flow, base, perturb=PERTURB[flow] if perturbed else 0.0)
    params, sampled_log_prob = adversary.sample_with_log_prob(2_000)
    with torch.no_grad():
        assert torch.allclose(adversary.log_prob(params), sampled_log_prob, atol=1e-6, rtol=0)
        grid, cell = SINUSOID.grid(GRID)
        mass = adversary.log_prob(grid).exp().sum() * cell
    assert abs(float(mass) - 1.0) < 1e-2
    outside = torch.tensor([[0.05, 1.0], [2.0, -0.1], [5.5, 4.0]], dtype=torch.float64)
    assert torch.isneginf(adversary.log_prob(outside)).all()


def test_default_spline_flow_on_two_identifiers_models_their_dependence() -> None:
    """One coupling is p(τ1)·p(τ2 | τ1): ln p_φ is not a sum of a function of τ1 and one of τ2."""
    adversary = make_adversary("spline", perturb=PERTURB["spline"])
    assert len(adversary.flow.layers) == 1
    corners = torch.cartesian_prod(torch.tensor([1.0, 4.0]), torch.tensor([0.5, 2.5]))
    with torch.no_grad():
        log_p = adversary.log_prob(corners.to(torch.float64))
    assert abs(float(log_p[0] + log_p[3] - log_p[1] - log_p[2])) > 1e-3


@pytest.mark.parametrize("flow", FLOWS)
@pytest.mark.parametrize("dim", [1, 3])
def test_density_normalizes_in_other_dimensions(flow: str, dim: int) -> None:
    space = TaskSpace([f"x{i}" for i in range(dim)], [-1.0] * dim, [2.0] * dim)
    adversary = make_adversary(flow, "normal", perturb=PERTURB[flow], space=space)
    grid, cell = space.grid(2_000 if dim == 1 else 30)
    with torch.no_grad():
        mass = adversary.log_prob(grid).exp().sum() * cell
        params, sampled_log_prob = adversary.sample_with_log_prob(1_000)
        assert torch.allclose(adversary.log_prob(params), sampled_log_prob, atol=1e-6, rtol=0)
    assert abs(float(mass) - 1.0) < 1e-2


@pytest.mark.parametrize("flow", FLOWS)
def test_log_prob_gradient_at_fixed_params_matches_finite_differences(flow: str) -> None:
    adversary = make_adversary(flow, "normal", perturb=PERTURB[flow])
    params = adversary.sample_params(16)
    parameters = list(adversary.parameters())
    direction = [torch.randn_like(p) for p in parameters]
    gradients = torch.autograd.grad(adversary.log_prob(params).sum(), parameters)
    analytic = sum((g * v).sum() for g, v in zip(gradients, direction, strict=True))
    step = 1e-6

    def shifted(sign: float) -> torch.Tensor:
        with torch.no_grad():
            for p, v in zip(parameters, direction, strict=True):
                p.add_(sign * step * v)
            value = adversary.log_prob(params).sum()
            for p, v in zip(parameters, direction, strict=True):
                p.sub_(sign * step * v)
        return value

    numeric = (shifted(1.0) - shifted(-1.0)) / (2 * step)
    assert torch.isclose(analytic, numeric, rtol=1e-5, atol=1e-7)


# --- contract 3: p_φ = p0 at initialization ------------------------------------------------------

@pytest.mark.parametrize("flow", FLOWS)
@pytest.mark.parametrize("base", BASES)
def test_equals_the_initial_distribution_at_init(flow: str, base: str) -> None:
    adversary = make_adversary(flow, base)
    grid, _ = SINUSOID.grid(50)
    with torch.no_grad():
        expected = adversary.base.log_prob(grid).to(torch.float64)
        assert torch.allclose(adversary.log_prob(grid), expected, atol=1e-10)
        image, log_det = adversary.flow(grid)
    assert torch.allclose(image, grid, atol=1e-12)
    assert log_det.abs().max() < 1e-12


@pytest.mark.parametrize("flow", FLOWS)
@pytest.mark.parametrize("dim", [1, 3])
def test_identity_at_init_in_other_dimensions(flow: str, dim: int) -> None:
    space = TaskSpace([f"x{i}" for i in range(dim)], [-1.0] * dim, [2.0] * dim)
    adversary = make_adversary(flow, "normal", space=space)
    params = adversary.base.sample_params(500)
    with torch.no_grad():
        image, log_det = adversary.flow(params)
    assert torch.allclose(image, params, atol=1e-12)
    assert log_det.abs().max() < 1e-12


# --- contract 4: the score-function gradient matches a finite difference of J --------------------

@pytest.mark.parametrize(("flow", "baseline", "batch"), [
    ("spline", "mean", 1_000), ("planar", "mean", 10_000), ("planar", "leave_one_out", 10_000)])
def test_score_function_gradient_matches_finite_difference(flow: str, baseline: str,
                                                           batch: int) -> None:
    lam, batches = 0.5, 32
    adversary = make_adversary(flow, "uniform", perturb=PERTURB[flow] / 2, seed=2)
    parameters = list(adversary.parameters())
    direction = [torch.randn_like(p) for p in parameters]
    estimates = []
    for _ in range(batches):
        params = adversary.sample_params(batch)
        initial = adversary.base.sample_params(batch)
        surrogate, _ = adversary_surrogate(adversary, params, toy_loss(params), lam, initial,
                                           baseline)
        gradients = torch.autograd.grad(surrogate, parameters)
        estimates.append(sum((g * v).sum() for g, v in zip(gradients, direction, strict=True)))
    estimates = torch.stack(estimates)
    estimate, standard_error = estimates.mean(), estimates.std() / math.sqrt(batches)

    step = 1e-5
    with torch.no_grad():
        values = []
        for sign in (1.0, -1.0):
            for p, v in zip(parameters, direction, strict=True):
                p.add_(sign * step * v)
            values.append(grid_objective(adversary, lam))
            for p, v in zip(parameters, direction, strict=True):
                p.sub_(sign * step * v)
    finite_difference = (values[0] - values[1]) / (2 * step)
    assert standard_error < 0.1 * finite_difference.abs()  # the comparison has power
    assert (estimate - finite_difference).abs() < 4 * standard_error


# --- contract 5: entropy -------------------------------------------------------------------------

@pytest.mark.parametrize("flow", FLOWS)
def test_entropy_at_init_is_that_of_p0(flow: str) -> None:
    adversary = make_adversary(flow, "uniform")
    # p0's log-density is float32-exact (BoxUniform returns the default dtype), hence 1e-6
    assert math.isclose(float(adversary.entropy(1_000)), math.log(4.9 * math.pi), abs_tol=1e-6)
    assert math.isclose(float(adversary.entropy(1_000)), 2.734, abs_tol=5e-4)  # paper's table
    kl, kl_sem = adversary.kl_from(adversary.base, 1_000)
    assert float(kl) == pytest.approx(0.0, abs=1e-6) and float(kl_sem) < 1e-6


@pytest.mark.parametrize("flow", FLOWS)
@pytest.mark.parametrize("base", BASES)
def test_entropy_and_kl_match_grid_quadrature(flow: str, base: str) -> None:
    adversary = make_adversary(flow, base, perturb=PERTURB[flow])
    n = 10_000
    torch.manual_seed(3)
    _, log_prob = adversary.sample_with_log_prob(n)
    torch.manual_seed(3)
    entropy = adversary.entropy(n)
    assert torch.isclose(entropy, -log_prob.mean())
    grid, cell = SINUSOID.grid(GRID)
    with torch.no_grad():
        log_p, log_p0 = adversary.log_prob(grid), adversary.base.log_prob(grid)
    grid_entropy = -cell * (log_p.exp() * log_p).sum()
    assert (entropy - grid_entropy).abs() < 4 * log_prob.std() / math.sqrt(n) + 1e-3
    torch.manual_seed(4)
    kl, kl_sem = adversary.kl_from(adversary.base, n)
    torch.manual_seed(4)
    initial = adversary.base.sample_params(n)
    with torch.no_grad():
        log_ratio = adversary.log_prob(initial) - adversary.base.log_prob(initial)
    terms = log_ratio.exp() - 1 - log_ratio
    assert (terms >= 0).all()  # each term of the estimate is non-negative
    assert torch.isclose(kl, terms.mean()) and torch.isclose(kl_sem, terms.std() / math.sqrt(n))
    grid_kl = cell * (log_p0.exp() * (log_p0 - log_p)).sum()
    assert grid_kl > 1e-3
    assert (kl - grid_kl).abs() < 4 * kl_sem + 1e-3


# --- the surrogate and its baselines -------------------------------------------------------------

def surrogate_gradient(adversary, params, losses, lam, initial, baseline):
    surrogate, stats = adversary_surrogate(adversary, params, losses, lam, initial, baseline)
    return torch.cat([g.flatten() for g in torch.autograd.grad(surrogate, adversary.parameters())])


def test_mean_baseline_is_a_scaled_leave_one_out_baseline() -> None:
    adversary = make_adversary("spline", "uniform", perturb=0.1)
    k = 25
    params, initial = adversary.sample_params(k), adversary.base.sample_params(64)
    losses = toy_loss(params)
    mean = surrogate_gradient(adversary, params, losses, 0.0, initial, "mean")
    loo = surrogate_gradient(adversary, params, losses, 0.0, initial, "leave_one_out")
    # L_k − mean(L) = (K − 1)/K · (L_k − mean of the others): same direction, both unbiased up to
    # this factor.
    assert torch.allclose(mean, (k - 1) / k * loo, atol=1e-10)
    assert mean.norm() > 1e-3
    lam_term = (surrogate_gradient(adversary, params, losses, 0.3, initial, "mean") - mean) / 0.3
    lam_term_loo = (surrogate_gradient(adversary, params, losses, 0.3, initial, "leave_one_out")
                    - loo) / 0.3
    assert torch.allclose(lam_term, lam_term_loo, atol=1e-8)


def test_constant_loss_gives_zero_loss_gradient() -> None:
    adversary = make_adversary("planar", "uniform", perturb=0.3)
    params, initial = adversary.sample_params(25), adversary.base.sample_params(64)
    losses = torch.full((25,), 0.7, dtype=torch.float64)
    for baseline in ("mean", "leave_one_out"):
        gradient = surrogate_gradient(adversary, params, losses, 0.0, initial, baseline)
        assert gradient.abs().max() < 1e-12
    _, stats = adversary_surrogate(adversary, params, losses, 0.2, initial)
    with torch.no_grad():
        expected = 0.7 + 0.2 * float(adversary.log_prob(initial).mean())
    assert stats["objective"] == pytest.approx(expected)


def test_bad_names_raise_config_errors() -> None:
    adversary = make_adversary("planar")
    params = adversary.sample_params(4)
    with pytest.raises(ConfigError, match="risk.ar.baseline"):
        adversary_surrogate(adversary, params, toy_loss(params), 0.1, params, "median")
    with pytest.raises(ConfigError, match="risk.ar.flow"):
        FlowAdversary(SINUSOID, BoxUniform(SINUSOID), "radial")
    with pytest.raises(ConfigError, match="risk.ar.flow_kwargs"):
        FlowAdversary(SINUSOID, BoxUniform(SINUSOID), "planar", bins=8)


# --- the follower: AdversarialPrinciple ----------------------------------------------------------

def make_principle(
    flow: str = "spline", seed: int = 0, total_updates: int = 1000, **options
) -> AdversarialPrinciple:
    """A principle on a fresh adversary, with the keys of ``risk.ar`` in ``options``."""
    return AdversarialPrinciple(make_adversary(flow, "uniform", seed=seed), ArOptions(**options),
                                total_updates=total_updates)


def run_updates(principle: AdversarialPrinciple, steps: int, k: int = 32) -> dict[str, float]:
    logs = {}
    for _ in range(steps):
        tasks = principle.propose(k)
        logs = principle.update(tasks, toy_loss(tasks["params"]))
    return logs


@pytest.mark.parametrize("flow", FLOWS)
def test_update_ascends_the_objective_and_keeps_samples_in_the_box(flow: str) -> None:
    lam = 0.2
    principle = make_principle(flow, lam=lam, lr=0.03, total_updates=25)
    assert isinstance(principle, RiskPrinciple)
    with torch.no_grad():
        before = grid_objective(principle.adversary, lam)
    logs = run_updates(principle, 25)
    with torch.no_grad():
        after = grid_objective(principle.adversary, lam)
    assert after > before + 0.1
    assert set(logs) == {"adversary/objective", "adversary/entropy", "adversary/kl_p0",
                         "adversary/lr", "adversary/grad_norm"}
    assert all(math.isfinite(v) for v in logs.values())
    assert logs["adversary/kl_p0"] > 0 and logs["adversary/entropy"] < SINUSOID.log_volume
    tasks = principle.propose(5_000)
    assert SINUSOID.contains(tasks["params"].to(torch.float64)).all()
    weights = principle.weights(toy_loss(tasks["params"]))
    assert torch.allclose(weights, torch.full_like(weights, 1 / 5_000))


def test_state_dict_round_trip_restores_exactly() -> None:
    principle = make_principle("spline", lr=0.01, total_updates=20)
    run_updates(principle, 3)
    buffer = io.BytesIO()
    torch.save(principle.state_dict(), buffer)
    buffer.seek(0)
    restored = make_principle("spline", seed=7, lr=0.01, total_updates=20)
    restored.load_state_dict(torch.load(buffer, weights_only=True))
    for a, b in zip(principle.parameters(), restored.parameters(), strict=True):
        assert torch.equal(a, b)
    torch.manual_seed(5)
    first = principle.propose(32)
    torch.manual_seed(5)
    first_restored = restored.propose(32)
    assert torch.equal(first["params"], first_restored["params"])
    assert torch.equal(first["log_prob"], first_restored["log_prob"])
    torch.manual_seed(11)
    logs = run_updates(principle, 2)
    torch.manual_seed(11)
    logs_restored = run_updates(restored, 2)
    assert logs == logs_restored
    for a, b in zip(principle.parameters(), restored.parameters(), strict=True):
        assert torch.equal(a, b)


def test_nan_loss_raises_without_changing_parameters() -> None:
    principle = make_principle("planar", lr=0.01)
    run_updates(principle, 2)
    before = [p.detach().clone() for p in principle.parameters()]
    tasks = principle.propose(8)
    losses = toy_loss(tasks["params"])
    losses[3] = float("nan")
    with pytest.raises(TrainingDiverged):
        principle.update(tasks, losses)
    for a, b in zip(before, principle.parameters(), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("updates_before", [0, 3])
def test_an_exploding_step_raises(updates_before) -> None:
    """A step that leaves φ or its log-densities non-finite stops the run (the trainer keeps its
    last checkpoint: tests/test_faults.py), also after Adam has state."""
    principle = make_principle("planar", lr=0.01, total_updates=50)
    run_updates(principle, updates_before)
    principle.optimizer.param_groups[0]["lr"] = 1e300
    tasks = principle.propose(8)
    with pytest.raises(TrainingDiverged, match="non-finite parameters or log-densities"):
        principle.update(tasks, toy_loss(tasks["params"]))


def test_propose_after_update_is_a_draw_from_the_updated_flow() -> None:
    """Every propose draws afresh from the current p_φ: after an update its tasks carry the new
    flow's log-densities, and nothing an update drew is handed out later."""
    principle = make_principle("spline", lr=0.05)
    run_updates(principle, 3, k=16)
    old = copy.deepcopy(principle.adversary)
    tasks = principle.propose(16)
    rng = torch.get_rng_state()
    principle.update(tasks, toy_loss(tasks["params"]))
    drawn = principle.propose(16)
    params = drawn["params"].to(torch.float64)
    with torch.no_grad():
        new_log_prob, old_log_prob = principle.adversary.log_prob(params), old.log_prob(params)
    assert torch.allclose(drawn["log_prob"].to(torch.float64), new_log_prob, atol=1e-5)
    assert (new_log_prob - old_log_prob).abs().max() > 1e-3  # the update moved p_φ there
    torch.set_rng_state(rng)  # the update draws p0 samples for its λ term, then propose draws
    principle.initial.sample_params(principle.follower.initial_samples)
    again = principle.propose(16)
    assert torch.equal(again["params"], drawn["params"])
    with torch.no_grad():  # φ changed by hand: the next draw follows it
        principle.adversary.flow.layers[0].prqct.unconditional_transform.unnormalized_widths.add_(
            torch.randn(1, 8, dtype=torch.float64))
        fresh = principle.propose(16)
        exact = principle.adversary.log_prob(fresh["params"].to(torch.float64))
    assert torch.allclose(fresh["log_prob"].to(torch.float64), exact, atol=1e-5)


@pytest.mark.parametrize(("kwargs", "key"), [
    ({"lam": -0.1}, "risk.ar.lam"), ({"update_every": 0}, "risk.ar.update_every"),
    ({"lr": 0.0}, "risk.ar.lr"), ({"total_updates": 0}, "risk.ar.total_updates"),
    ({"grad_clip": 0.0}, "risk.ar.grad_clip"), ({"baseline": "max"}, "risk.ar.baseline"),
    ({"initial_samples": 0}, "risk.ar.initial_samples"),
])
def test_principle_rejects_bad_config(kwargs: dict, key: str) -> None:
    with pytest.raises(ConfigError) as error:
        make_principle("planar", **kwargs)
    assert error.value.key == key


def test_erm_samples_p0_with_uniform_weights() -> None:
    initial = make_base("normal")
    principle = ERMPrinciple(initial)
    assert isinstance(principle, RiskPrinciple) and principle.update_every == 0
    tasks = principle.propose(500)
    params = tasks["params"].to(torch.float64)
    assert SINUSOID.contains(params).all()
    assert torch.allclose(tasks["log_prob"].to(torch.float64), initial.log_prob(params), atol=1e-5)
    weights = principle.weights(torch.rand(10))
    assert torch.allclose(weights, torch.full((10,), 0.1))
    assert principle.update(tasks, torch.rand(500)) == {}


# --- the density plot ----------------------------------------------------------------------------

def test_plot_density_draws_both_densities(tmp_path) -> None:
    adversary = make_adversary("spline", "normal", perturb=0.1)
    path = tmp_path / "density.png"
    figure = plot_density(adversary, adversary.base, path, points_per_axis=30)
    assert path.stat().st_size > 0
    images = [axis.images[0] for axis in figure.axes if axis.images]
    assert len(images) == 2 and len(figure.axes) == 3  # two heat maps and one shared colorbar
    assert images[0].get_clim() == images[1].get_clim()  # one colour scale for both
    grid, _ = SINUSOID.grid(30)
    with torch.no_grad():
        for image, distribution in zip(images, (adversary, adversary.base), strict=True):
            expected = distribution.log_prob(grid).exp().reshape(30, 30).T.numpy()
            assert abs(image.get_array() - expected).max() < 1e-12
    assert [axis.get_xlabel() for axis in figure.axes if axis.images] == ["amplitude"] * 2
    assert [axis.get_ylabel() for axis in figure.axes if axis.images] == ["phase"] * 2


def test_plot_density_one_and_three_identifiers(tmp_path) -> None:
    """One identifier: p_φ and p0 drawn as their densities on the plotted points. Three: each
    pair below the diagonal drawn as its marginal density, the third identifier integrated out
    (uniform on [0, 1] × [0, 2] × [0, 4]: 1/2, 1/4 and 1/8 for the pairs ab, ac and bc)."""
    line = TaskSpace(["mass"], [0.5], [2.0])
    adversary = make_adversary("planar", perturb=0.3, space=line)
    figure = plot_density(adversary, adversary.base, tmp_path / "a.png")
    for drawn, distribution in zip(figure.axes[0].lines, (adversary, adversary.base), strict=True):
        points = torch.as_tensor(np.asarray(drawn.get_xdata()), dtype=torch.float64)[:, None]
        with torch.no_grad():
            expected = distribution.log_prob(points).exp().numpy()
        assert np.abs(np.asarray(drawn.get_ydata()) - expected).max() < 1e-12
    cube = TaskSpace(["a", "b", "c"], [0, 0, 0], [1, 2, 4])
    figure = plot_density(BoxUniform(cube), BoxUniform(cube), tmp_path / "b.png")
    marginals = [np.asarray(axis.images[0].get_array()) for axis in figure.axes if axis.images]
    assert len(marginals) == 3  # the pairs below the diagonal
    for marginal, density in zip(marginals, (1 / 2, 1 / 4, 1 / 8), strict=True):
        assert np.allclose(marginal, density, rtol=1e-6)


# --- the adversary's signal options (docs/meta-rl.md) ---------------------------------------------

def test_standardized_advantages_make_the_update_free_of_the_loss_scale() -> None:
    """With ``standardize`` the surrogate's gradient at losses c·L + b equals that at L for any
    c > 0 and b, λ included: one λ serves MSE and returns. Without it, the loss term scales
    with c and λ's weight against it shrinks by c."""
    adversary = make_adversary("spline", "uniform", perturb=0.1)
    params, initial = adversary.sample_params(20), adversary.base.sample_params(64)
    losses = toy_loss(params)

    def gradient(values: torch.Tensor, standardize: bool) -> torch.Tensor:
        surrogate, _ = adversary_surrogate(adversary, params, values, 0.3, initial,
                                           standardize=standardize)
        return torch.cat([g.flatten() for g in torch.autograd.grad(surrogate,
                                                                   adversary.parameters())])

    reference = gradient(losses, True)
    assert torch.allclose(gradient(25.0 * losses - 3.0, True), reference, atol=1e-10)
    lam_term = _lam_only(adversary, initial, 0.3)
    loss_term = gradient(losses, False) - lam_term
    assert loss_term.norm() > 1e-3
    assert torch.allclose(gradient(25.0 * losses, False), 25.0 * loss_term + lam_term, atol=1e-8)


def _lam_only(adversary: FlowAdversary, initial: torch.Tensor, lam: float) -> torch.Tensor:
    """The λ term's gradient alone (the loss term vanishes for equal losses)."""
    params = adversary.sample_params(4)
    surrogate, _ = adversary_surrogate(adversary, params, torch.ones(4, dtype=torch.float64),
                                       lam, initial)
    return torch.cat([g.flatten() for g in torch.autograd.grad(surrogate,
                                                               adversary.parameters())])


def test_regret_signal_ascends_the_loss_minus_the_reference() -> None:
    """``signal="regret"`` updates p_φ exactly as the loss signal would on L − L*(τ)."""
    reference = lambda params: 2.0 * params[:, 0].to(torch.float64)  # noqa: E731
    results = []
    for signal, shift in (("regret", False), ("loss", True)):
        adversary = make_adversary("spline", "uniform", perturb=0.1, seed=5)
        principle = AdversarialPrinciple(
            adversary, ArOptions(lam=0.2, signal=signal), total_updates=10,
            reference_loss=reference if signal == "regret" else None)
        torch.manual_seed(6)
        tasks = principle.propose(16)
        losses = toy_loss(tasks["params"])
        if shift:
            losses = losses - reference(tasks["params"])
        torch.manual_seed(7)
        stats = principle.update(tasks, losses)
        results.append((stats["adversary/objective"],
                        [p.detach().clone() for p in adversary.parameters()]))
    assert results[0][0] == pytest.approx(results[1][0])
    assert all(torch.equal(a, b) for a, b in zip(results[0][1], results[1][1], strict=True))


def test_regret_without_a_reference_is_refused() -> None:
    with pytest.raises(ConfigError, match="risk.ar.signal"):
        AdversarialPrinciple(make_adversary("spline"), ArOptions(signal="regret"))


# --- the natural step: a move of fixed KL, whatever the parametrization --------------------------

CHEETAH_MASS = TaskSpace(["goal_velocity", "mass_scale"], [0.0, 0.75], [2.0, 1.25])


def test_fisher_vector_product_is_the_mean_outer_product_of_scores() -> None:
    """(1/n) Σ_i ∇ln p_φ(τ_i) ∇ln p_φ(τ_i)ᵀ v, from per-sample gradients, equals the product of
    the reverse-over-reverse trick, on a spline flow off its identity."""
    adversary = make_adversary("spline", perturb=0.1, space=CHEETAH_MASS)
    phi = list(adversary.parameters())
    draws = adversary.sample_params(6)
    product = fisher_vector_product(adversary.log_prob(draws), phi, damping=0.25)
    scores = torch.stack([flatten(torch.autograd.grad(adversary.log_prob(draw[None])[0], phi))
                          for draw in draws])
    vector = torch.randn(scores.shape[1], dtype=torch.float64)
    expected = scores.T @ (scores @ vector) / len(draws) + 0.25 * vector
    assert torch.allclose(product(vector), expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("flow", ["spline", "planar"])
@pytest.mark.parametrize("max_kl", [0.002, 0.02])
def test_natural_step_moves_p_phi_by_its_kl(flow: str, max_kl: float) -> None:
    """The measured KL(p_φt ‖ p_φt+1) of a natural step, on 20,000 fresh draws, is δ to within
    the Fisher matrix's estimate from M draws and its damping (which only shortens a step)."""
    principle = make_principle(flow, step="natural", max_kl=max_kl)
    run_updates(principle, 3)
    draws = principle.adversary.sample_params(20_000)
    with torch.no_grad():
        before = principle.adversary.log_prob(draws)
    logs = run_updates(principle, 1)
    with torch.no_grad():
        after = principle.adversary.log_prob(draws)
    measured = float(kl_estimate(before, after))
    assert 0.3 * max_kl < measured < 1.5 * max_kl
    assert set(logs) == {"adversary/objective", "adversary/entropy", "adversary/kl_p0",
                         "adversary/step_kl", "adversary/grad_norm"}
    assert logs["adversary/step_kl"] == pytest.approx(measured, rel=0.5)


def coordinate_kl(coordinate: int, step: dict, updates: int, seed: int = 0) -> float:
    """KL(p0 ‖ p_φ) after ``updates`` follower steps against the fixed loss L(τ) = the
    ``coordinate``-th identifier scaled to [0, 1], plus a little noise."""
    adversary = make_adversary("spline", seed=seed, space=CHEETAH_MASS)
    principle = AdversarialPrinciple(adversary, ArOptions(lam=0.0, **step), total_updates=updates)
    low, high = CHEETAH_MASS.bounds(torch.float64)
    for _ in range(updates):
        tasks = principle.propose(20)
        scaled = (tasks["params"][:, coordinate] - low[coordinate]) / (high - low)[coordinate]
        principle.update(tasks, scaled + 0.05 * torch.randn(20, dtype=torch.float64))
    return float(adversary.kl_from(adversary.base, 4096)[0])


def test_natural_step_moves_every_coordinate_equally_easily() -> None:
    """Under one budget against one loss, the KL reachable along each coordinate of a 2-D box is
    within 2× of the other's, so the identifiers' order does not decide what the adversary can
    do. Adam at the same budget's scale moves the second coordinate (through the coupling's
    conditioner network) about fifty times further than the first (direct spline parameters)."""
    natural = {"step": "natural", "max_kl": 0.005}
    first, second = coordinate_kl(0, natural, 20), coordinate_kl(1, natural, 20)
    assert first > 0.1 and second > 0.1
    assert 0.5 < first / second < 2.0
    adam = {"lr": 0.5 / 20, "grad_clip": 1.0}
    assert coordinate_kl(1, adam, 20) > 10 * coordinate_kl(0, adam, 20)


def test_natural_steps_reach_further_in_a_longer_run() -> None:
    """The natural step's budget is per update, not per run: against a fixed loss, 4× the
    updates reach clearly further (about 12×), where Adam at rate 0.5 / updates does not."""
    natural = {"step": "natural", "max_kl": 0.002}
    assert coordinate_kl(0, natural, 40) > 3 * coordinate_kl(0, natural, 10)
    short, long = (coordinate_kl(0, {"lr": 0.5 / n}, n) for n in (10, 40))
    assert long < 1.5 * short
