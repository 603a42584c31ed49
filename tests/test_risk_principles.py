"""Risk principles dr (tail risk), tr (worst case) and dro (group DRO) on hand-made losses, and
dr in the game loop."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from armeta_rl.collectors.regression import SinusoidCollector
from armeta_rl.config import TrainerConfig
from armeta_rl.errors import ConfigError
from armeta_rl.learners.maml import MAMLLeader
from armeta_rl.learners.mlp import make_mlp
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.risk.erm import ERMPrinciple
from armeta_rl.risk.groups import (
    DroOptions,
    GroupDROPrinciple,
    TrOptions,
    WorstCasePrinciple,
    project_to_simplex,
)
from armeta_rl.risk.tail import DrOptions, TailRiskPrinciple, tail_risk
from armeta_rl.tasks import BoxUniform, TaskSpace
from armeta_rl.trainers.evaluation import cvar
from armeta_rl.trainers.game import GameTrainer

SPACE = TaskSpace(("amplitude", "phase"), (0.1, 0.0), (5.0, math.pi))


def make_tasks(params: torch.Tensor) -> TensorDict:
    p0 = BoxUniform(SPACE)
    return TensorDict({"params": params, "log_prob": p0.log_prob(params).float()},
                      batch_size=[params.shape[0]])


def cell_centers(cells: list[tuple[int, int]], per_axis: int = 3) -> torch.Tensor:
    """Parameters at the centre of grid cells (i along amplitude, j along phase)."""
    low, high = SPACE.bounds(torch.float64)
    index = torch.tensor(cells, dtype=torch.float64)
    return low + (index + 0.5) / per_axis * (high - low)


def on_simplex(q: torch.Tensor) -> bool:
    tolerance = 1e-12 if q.dtype == torch.float64 else 1e-6
    return bool((q >= 0).all()) and math.isclose(float(q.sum()), 1.0, abs_tol=tolerance)


# --- dr: tail risk ------------------------------------------------------------------------------


def test_tail_risk_keeps_exactly_the_worst_half():
    torch.manual_seed(0)
    losses = torch.rand(10)
    weights = TailRiskPrinciple(BoxUniform(SPACE), DrOptions(alpha=0.5)).weights(losses)
    kept = weights > 0
    assert int(kept.sum()) == 5
    assert set(kept.nonzero().flatten().tolist()) == set(torch.argsort(losses)[5:].tolist())
    assert torch.allclose(weights[kept], torch.full((5,), 0.2))
    assert losses[kept].min() > losses[~kept].max()


@pytest.mark.parametrize(("alpha", "batch", "kept"), [(0.5, 7, 4), (0.7, 10, 3), (0.3, 10, 7),
                                                       (0.9, 5, 1), (0.99, 4, 1)])
def test_tail_size_is_the_ceiling_of_the_tail_mass(alpha, batch, kept):
    principle = TailRiskPrinciple(BoxUniform(SPACE), DrOptions(alpha=alpha))
    weights = principle.weights(torch.randn(batch))
    assert int((weights > 0).sum()) == kept
    assert on_simplex(weights)


@pytest.mark.parametrize("alpha", [0.25, 0.5, 0.75])
def test_tail_weighted_loss_is_the_rockafellar_uryasev_cvar(alpha):
    """Σ w L = min_v v + E[(L − v)_+] / (1 − α) when (1 − α)·K is an integer."""
    torch.manual_seed(1)
    losses = torch.randn(16, dtype=torch.float64).exp()
    principle = TailRiskPrinciple(BoxUniform(SPACE), DrOptions(alpha=alpha))
    candidates = torch.cat([losses, torch.linspace(0, float(losses.max()), 2001,
                                                   dtype=torch.float64)])
    objective = candidates + (losses[None] - candidates[:, None]).clamp_min(0).mean(1) / (1 - alpha)
    assert float((principle.weights(losses) * losses).sum()) == pytest.approx(
        float(objective.min()), rel=1e-12)
    logs = principle.update(make_tasks(torch.zeros(16, 2) + 1.0), losses)
    assert logs["risk/cvar"] == pytest.approx(float(objective.min()), rel=1e-12)
    var = logs["risk/var"]  # a minimizer of the Rockafellar–Uryasev objective
    assert var + float((losses - var).clamp_min(0).mean()) / (1 - alpha) == pytest.approx(
        float(objective.min()), rel=1e-12)


@pytest.mark.parametrize("alpha", [0.3, 0.5, 0.9])
@pytest.mark.parametrize("batch", [1, 7, 10, 25])
def test_the_training_tail_risk_is_the_evaluation_cvar(alpha, batch):
    """Σ_k ω_k L_k of Eq. (21), which DR minimizes and logs, and the meta-test CVaR_α are one
    number, tail size included, whether or not (1 − α)·K is an integer."""
    torch.manual_seed(batch)
    losses = torch.rand(batch, dtype=torch.float64) * 5
    assert float(tail_risk(losses, alpha)) == pytest.approx(cvar(losses, alpha), rel=1e-12)
    assert cvar(-losses, alpha, higher_better=True) == pytest.approx(-cvar(losses, alpha),
                                                                     rel=1e-12)


def test_tail_risk_proposes_from_p0_and_oversamples():
    p0 = BoxUniform(SPACE)
    plain = TailRiskPrinciple(p0)
    over = TailRiskPrinciple(p0, DrOptions(alpha=0.5, oversample=True))
    torch.manual_seed(3)
    tasks = plain.propose(8)
    torch.manual_seed(3)
    assert torch.equal(tasks["params"], p0.sample(8)["params"])
    candidates = over.propose(8)
    assert candidates.batch_size == torch.Size([16])
    assert bool(SPACE.contains(candidates["params"]).all())
    assert int((over.weights(torch.rand(16)) > 0).sum()) == 8
    assert isinstance(plain, RiskPrinciple)
    # no follower: its update reports the tail of each step's own losses, at no extra evaluation
    assert plain.update_every == 1 and not plain.needs_next_losses


def test_dr_training_logs_the_tail_of_each_steps_losses():
    """In the game loop DR's update reads the step's own losses: its CVaR is the objective the
    leader just minimized (losses at θ_{t+1} would differ), and its VaR is at most that; it
    draws no random numbers (the stream ends where an ERM loop's, with the same proposals, ends)."""
    def train(principle) -> tuple[list[dict[str, float]], torch.Tensor]:
        torch.manual_seed(0)
        leader = MAMLLeader(make_mlp(1, 1, (8, 8)), SinusoidCollector(5, 5))
        trainer = GameTrainer(leader, principle,
                              TrainerConfig(iterations=3, meta_batch=8, progress=False))
        return [trainer.train_iteration() for _ in range(3)], torch.get_rng_state()

    logs, rng = train(TailRiskPrinciple(BoxUniform(SPACE), DrOptions(alpha=0.5)))
    for scalars in logs:
        assert scalars["risk/cvar"] == pytest.approx(scalars["train/leader_loss"], rel=1e-6)
        assert scalars["risk/var"] <= scalars["risk/cvar"]
        assert scalars["train/task_loss_mean"] <= scalars["risk/cvar"]
    _, erm_rng = train(ERMPrinciple(BoxUniform(SPACE)))
    assert torch.equal(rng, erm_rng)


@pytest.mark.parametrize("alpha", [0.0, 1.0, -0.1, 1.5, "half", None])
def test_tail_risk_rejects_bad_alpha(alpha):
    with pytest.raises(ConfigError) as error:
        TailRiskPrinciple(BoxUniform(SPACE), DrOptions(alpha=alpha))
    assert error.value.key == "risk.dr.alpha"


# --- Euclidean projection onto the simplex -------------------------------------------------------


def bisection_projection(v: torch.Tensor) -> torch.Tensor:
    """Reference: q = max(v − τ, 0) with Σ q = 1, τ found by bisection (monotone in τ)."""
    low, high = float(v.min()) - 1.0, float(v.max())
    for _ in range(200):
        tau = 0.5 * (low + high)
        if float((v - tau).clamp_min(0).sum()) > 1.0:
            low = tau
        else:
            high = tau
    return (v - 0.5 * (low + high)).clamp_min(0)


def test_simplex_projection_matches_bisection_reference():
    torch.manual_seed(4)
    for dim in (1, 2, 3, 9, 27):
        for scale in (0.1, 1.0, 10.0):
            v = scale * torch.randn(dim, dtype=torch.float64)
            q = project_to_simplex(v)
            assert on_simplex(q)
            assert torch.allclose(q, bisection_projection(v), atol=1e-10)


def test_simplex_projection_is_the_closest_point_among_many():
    torch.manual_seed(5)
    points = torch.distributions.Dirichlet(torch.full((3,), 0.5, dtype=torch.float64)).sample(
        (20000,))
    points = torch.cat([points, torch.eye(3, dtype=torch.float64)])
    for _ in range(20):
        v = 2 * torch.randn(3, dtype=torch.float64)
        q = project_to_simplex(v)
        assert float((q - v).norm()) <= float((points - v).norm(dim=1).min()) + 1e-12


def test_simplex_projection_known_cases():
    inside = torch.tensor([0.2, 0.3, 0.5], dtype=torch.float64)
    assert torch.allclose(project_to_simplex(inside), inside)
    assert torch.allclose(project_to_simplex(torch.full((4,), 7.0, dtype=torch.float64)),
                          torch.full((4,), 0.25, dtype=torch.float64))
    assert torch.allclose(project_to_simplex(torch.tensor([2.0, 0.0, -1.0], dtype=torch.float64)),
                          torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    assert torch.allclose(project_to_simplex(torch.tensor([1.0, 0.5], dtype=torch.float64)),
                          torch.tensor([0.75, 0.25], dtype=torch.float64))


# --- tr and dro: group weights --------------------------------------------------------------------

GROUP_PRINCIPLES = [(WorstCasePrinciple, TrOptions), (GroupDROPrinciple, DroOptions)]


@pytest.mark.parametrize("per_axis", [1, 3, 4])
def test_groups_are_the_grid_cells(per_axis):
    principle = WorstCasePrinciple(BoxUniform(SPACE), TrOptions(groups_per_axis=per_axis))
    assert principle.num_groups == per_axis**2
    torch.manual_seed(6)
    params = BoxUniform(SPACE).sample_params(500)
    params = torch.cat([params, torch.stack(SPACE.bounds(torch.float64))])
    low, high = SPACE.bounds(torch.float64)
    inner_edges = [torch.linspace(lo, hi, per_axis + 1, dtype=torch.float64)[1:-1]
                   for lo, hi in zip(low.tolist(), high.tolist(), strict=True)]
    cells = [torch.bucketize(params[:, i].contiguous(), inner_edges[i], right=True)
             for i in range(2)]
    assert torch.equal(principle.group_of(params), cells[0] * per_axis + cells[1])


@pytest.mark.parametrize(("kind", "options"), GROUP_PRINCIPLES)
def test_group_weights_divide_q_among_each_groups_tasks(kind, options):
    principle = kind(BoxUniform(SPACE), options(groups_per_axis=3))
    assert principle.update_every == 1 and isinstance(principle, RiskPrinciple)
    # uniform q, every group present equally often: plain ERM
    tasks = make_tasks(cell_centers([(i, j) for i in range(3) for j in range(3)] * 2))
    assert torch.allclose(principle.weights(torch.rand(18), tasks), torch.full((18,), 1 / 18))
    # groups 0 (one task) and 8 (three tasks) only: renormalized over the groups present
    tasks = make_tasks(cell_centers([(0, 0), (2, 2), (2, 2), (2, 2)]))
    expected = torch.tensor([1 / 2, 1 / 6, 1 / 6, 1 / 6])
    assert torch.allclose(principle.weights(torch.rand(4), tasks), expected)
    # all of q on group 4: only its tasks count, equally
    q = torch.zeros(9, dtype=torch.float64)
    q[4] = 1.0
    principle.load_state_dict({"q": q})
    tasks = make_tasks(cell_centers([(1, 1), (0, 2), (1, 1), (2, 0)]))
    assert torch.allclose(principle.weights(torch.rand(4), tasks), torch.tensor([0.5, 0, 0.5, 0]))
    # ... and a batch that misses group 4: its groups share the weight equally, no 0/0
    tasks = make_tasks(cell_centers([(0, 0), (2, 2), (2, 2)]))
    assert torch.allclose(principle.weights(torch.rand(3), tasks), torch.tensor([0.5, 0.25, 0.25]))


@pytest.mark.parametrize(("kind", "options"), GROUP_PRINCIPLES)
def test_group_weights_are_a_function_of_the_losses_and_their_tasks(kind, options):
    """Weights depend on the tasks passed in, not on what propose saw: a copy of the batch, or
    a second propose in between, gives the same weights."""
    principle = kind(BoxUniform(SPACE), options(groups_per_axis=3))
    principle.load_state_dict({"q": torch.softmax(torch.randn(9, dtype=torch.float64), 0)})
    torch.manual_seed(7)
    tasks = principle.propose(32)
    losses = torch.rand(32)
    weights = principle.weights(losses, tasks)
    other = principle.propose(32)
    assert torch.equal(weights, principle.weights(losses, tasks.clone()))
    assert not torch.equal(weights, principle.weights(losses, other))
    assert on_simplex(weights)
    with pytest.raises(ValueError):
        principle.weights(torch.rand(31), tasks)


@pytest.mark.parametrize(("kind", "options"), GROUP_PRINCIPLES)
def test_group_weights_move_toward_the_worst_group_and_stay_on_the_simplex(kind, options):
    principle = kind(BoxUniform(SPACE), options(groups_per_axis=3, step_size=0.05))
    cells = [(i, j) for i in range(3) for j in range(3)] * 2
    tasks = make_tasks(cell_centers(cells))
    group_loss = torch.tensor([1.0, 0.5, 0.8, 1.2, 3.0, 0.1, 0.9, 1.1, 0.4])
    losses = torch.cat([group_loss - 0.2, group_loss + 0.2])  # two tasks per group, same mean
    previous = principle.q.clone()
    for _ in range(40):
        logs = principle.update(tasks, losses)
        q = principle.q
        assert on_simplex(q)
        assert q[4] > previous[4] or q[4] == 1.0  # tr stops at the vertex
        assert logs["risk/max_group_weight"] == pytest.approx(float(q.max()))
        assert logs["risk/worst_group_loss"] == pytest.approx(3.0)
        previous = q.clone()
    assert int(principle.q.argmax()) == 4


def test_worst_case_reaches_the_vertex_of_the_worst_group():
    principle = WorstCasePrinciple(BoxUniform(SPACE), TrOptions(groups_per_axis=3, step_size=0.1))
    tasks = make_tasks(cell_centers([(i, j) for i in range(3) for j in range(3)]))
    losses = torch.tensor([1.0, 0.5, 0.8, 1.2, 3.0, 0.1, 0.9, 1.1, 0.4])
    first = project_to_simplex(principle.q + 0.1 * losses.double())
    principle.update(tasks, losses)
    assert torch.allclose(principle.q, first)
    for _ in range(50):
        principle.update(tasks, losses)
    assert torch.equal(principle.q, torch.eye(9, dtype=torch.float64)[4])


def test_group_dro_is_exponentiated_gradient():
    """After t steps with fixed group means L̄: ln(q_g / q_h) = η·t·(L̄_g − L̄_h), L̄ = 0 if absent."""
    principle = GroupDROPrinciple(BoxUniform(SPACE), DroOptions(groups_per_axis=3, step_size=0.02))
    tasks = make_tasks(cell_centers([(0, 0), (0, 0), (1, 1), (2, 2)]))
    losses = torch.tensor([1.0, 3.0, 4.0, 0.5])  # means: g0 = 2, g4 = 4, g8 = 0.5, others absent
    for _ in range(25):
        principle.update(tasks, losses)
    log_q = principle.q.log()
    mean = torch.zeros(9, dtype=torch.float64)
    mean[[0, 4, 8]] = torch.tensor([2.0, 4.0, 0.5], dtype=torch.float64)
    assert torch.allclose(log_q - log_q[1], 0.02 * 25 * mean, atol=1e-12)
    assert on_simplex(principle.q)


@pytest.mark.parametrize(("kind", "options"), GROUP_PRINCIPLES)
def test_group_state_dict_round_trip(kind, options):
    principle = kind(BoxUniform(SPACE), options(groups_per_axis=3))
    tasks = make_tasks(cell_centers([(0, 1), (2, 2)]))
    principle.update(tasks, torch.tensor([2.0, 0.5]))
    restored = kind(BoxUniform(SPACE), options(groups_per_axis=3))
    restored.load_state_dict(principle.state_dict())
    assert torch.equal(restored.q, principle.q)
    assert not torch.equal(restored.q, torch.full((9,), 1 / 9, dtype=torch.float64))


@pytest.mark.parametrize(("options", "prefix"), [(TrOptions, "risk.tr"), (DroOptions, "risk.dro")])
@pytest.mark.parametrize(("key", "value"), [("groups_per_axis", 0), ("groups_per_axis", 2.5),
                                            ("step_size", 0.0), ("step_size", -1.0),
                                            ("step_size", math.inf)])
def test_group_options_reject_bad_config(options, prefix, key, value):
    with pytest.raises(ConfigError) as error:
        options(**{key: value})
    assert error.value.key == f"{prefix}.{key}"
