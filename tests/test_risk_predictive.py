"""MPTS and PDTS (risk/predictive.py, risk/mpts.py, risk/pdts.py): the risk model learns a known
loss landscape, the acquisitions pick what their equations say, PDTS's diversity spreads the
picks, batched passes equal per-task references, and bad input is refused."""

from __future__ import annotations

import itertools
import math
from copy import deepcopy

import pytest
import torch

from armeta_rl.cli import train
from armeta_rl.config import validate
from armeta_rl.errors import ConfigError, TrainingDiverged
from armeta_rl.risk import mpts, pdts
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.risk.mpts import (
    MptsOptions,
    MPTSPrinciple,
    mixed_selection,
    predictive_moments,
    top_b,
    ucb_scores,
)
from armeta_rl.risk.pdts import (
    PdtsOptions,
    PDTSPrinciple,
    greedy_diverse_subset,
    mean_pairwise_distance,
    posterior_sample_risks,
)
from armeta_rl.risk.predictive import (
    RiskPredictiveModel,
    negative_elbo,
    pearson,
    reconstruction_error,
)
from armeta_rl.risk.sampling import PrincipleSampler
from armeta_rl.tasks import BoxUniform, TaskSpace
from conftest import compose_train, moved_players, players_of

SPACE = TaskSpace(("amplitude", "phase"), (0.1, 0.0), (5.0, math.pi))
HARDEST = torch.tensor([0.85, 0.15])  # the peak of the landscape, in unit-box coordinates
FAST = {"lr": 5e-3, "steps": 5, "standardize": True}  # a quick-learning model for the tests


def subset_objective(risks: torch.Tensor, points: torch.Tensor, diversity: float) -> torch.Tensor:
    """The objective of Eq. (12c) for one subset, Σ_i ℓ̂_i + γ·S(T^B), from the subset's risks
    ``[B]`` and points ``[B, d]``: the reference the greedy subset is scored against."""
    return risks.sum() + diversity * mean_pairwise_distance(points)


def landscape(params: torch.Tensor) -> torch.Tensor:
    """A loss with one known hardest region: 1 + 4·exp(−|u − c|² / (2·0.15²)) in unit coords."""
    unit = SPACE.to_unit(params.to(torch.float64))
    return 1.0 + 4.0 * torch.exp(-(unit - HARDEST).square().sum(-1) / (2 * 0.15**2))


def near_peak(params: torch.Tensor, radius: float = 0.25) -> torch.Tensor:
    return (SPACE.to_unit(params.to(torch.float64)) - HARDEST).norm(dim=-1) < radius


def train_on_landscape(principle, iterations: int, batch: int = 16) -> list[torch.Tensor]:
    """Stream the principle's own proposals with the landscape's losses (plus noise); returns
    the proposals of every iteration."""
    proposals = []
    for _ in range(iterations):
        tasks = principle.propose(batch)
        losses = landscape(tasks["params"]) + 0.05 * torch.randn(batch, dtype=torch.float64)
        principle.update(tasks, losses)
        proposals.append(tasks["params"])
    return proposals


def grid_predictions(principle) -> tuple[torch.Tensor, torch.Tensor]:
    """The model's prediction (posterior mean z) and the landscape on a 15 × 15 grid."""
    grid, _ = SPACE.grid(15)
    with torch.no_grad():
        predicted = principle.model.predict(principle.unit(grid),
                                            principle.posterior_loc.unsqueeze(0))[0]
    return predicted.double(), landscape(grid)


# --- the risk model ------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["mpts", "pdts"])
def test_risk_model_learns_a_landscape_with_a_known_hardest_region(kind):
    """Trained online on batches from p0 (an endless warm-up), the model's predictions come to
    rank the box as the landscape does (Pearson > 0.9 on a grid) and its predicted hardest cell
    lies in the known hardest region; then its acquisition's picks carry over 80% of the excess
    loss (over the pseudo-batch's mean) that an oracle picking the true worst B would get."""
    torch.manual_seed(0)
    options = {**FAST, "warmup": 10**9}
    principle = (MPTSPrinciple(BoxUniform(SPACE), MptsOptions(**options)) if kind == "mpts" else
                 PDTSPrinciple(BoxUniform(SPACE), PdtsOptions(**options, candidate_ratio=8.0)))
    train_on_landscape(principle, 200)
    predicted, truth = grid_predictions(principle)
    assert float(pearson(predicted, truth)) > 0.9
    grid, _ = SPACE.grid(15)
    assert bool(near_peak(grid[predicted.argmax()].unsqueeze(0)))
    principle.warmup = 0
    captured = []
    for draw in range(50):
        torch.manual_seed(100 + draw)
        picked = landscape(principle.propose(16)["params"])
        torch.manual_seed(100 + draw)
        pool = landscape(principle.initial.sample(principle.pool_size(16))["params"])
        best = pool.topk(16).values.mean()  # the oracle's pick of the same pseudo-batch
        captured.append(float((picked.mean() - pool.mean()) / (best - pool.mean())))
    assert sum(captured) / len(captured) > 0.8


def test_mpts_selection_runs_the_worst_part_of_each_pseudo_batch():
    """Online on its own proposals, MPTS with B̂ = 2B comes to train on about the worst half of
    each pseudo-batch: its batches fall in the hardest region about twice as often as p0's."""
    torch.manual_seed(0)
    principle = MPTSPrinciple(BoxUniform(SPACE), MptsOptions(**FAST))
    proposals = train_on_landscape(principle, 300)
    p0_share = float(near_peak(BoxUniform(SPACE).sample_params(100_000)).double().mean())
    assert float(near_peak(torch.cat(proposals[-100:])).double().mean()) > 1.6 * p0_share


def test_the_streaming_prior_holds_the_posterior_near_the_last_one():
    """Eq. (5)'s KL to the previous posterior: with a large β the new posterior barely moves from
    the stored one; with β = 0 it moves freely. The stored posterior is the model's q(z | H_t)."""
    def moved(kl_weight: float) -> float:
        torch.manual_seed(1)
        principle = MPTSPrinciple(BoxUniform(SPACE), MptsOptions(lr=0.01, steps=20,
                                                                 kl_weight=kl_weight))
        train_on_landscape(principle, 3)
        before = principle.posterior_loc.clone(), principle.posterior_scale.clone()
        tasks = principle.propose(16)
        principle.update(tasks, 10 * landscape(tasks["params"]))
        with torch.no_grad():
            stored = principle.model.posterior(principle.unit(tasks["params"]),
                                               principle.labels(10 * landscape(tasks["params"])
                                                                .float()))
        assert torch.allclose(stored[0], principle.posterior_loc, atol=1e-6)
        assert torch.allclose(stored[1], principle.posterior_scale, atol=1e-6)
        return float(torch.distributions.kl_divergence(
            torch.distributions.Normal(principle.posterior_loc, principle.posterior_scale),
            torch.distributions.Normal(*before)).sum())

    assert moved(1000.0) < 0.1 * moved(0.0)


def test_batched_predictions_and_elbo_equal_per_task_references():
    torch.manual_seed(2)
    model = RiskPredictiveModel(2, hidden=10, latent=4)
    unit, labels = torch.rand(7, 2), torch.rand(7)
    z = torch.randn(5, 4)
    batched = model.predict(unit, z)
    for s, i in itertools.product(range(5), range(7)):
        single = model.decoder(torch.cat([unit[i], z[s]]))
        assert torch.allclose(batched[s, i], single[0], atol=1e-6)
    permutation = torch.randperm(7)
    for a, b in zip(model.posterior(unit, labels), model.posterior(unit[permutation],
                                                                   labels[permutation])):
        assert torch.allclose(a, b, atol=1e-6)  # q(z | H) does not depend on the task order
    prior = torch.zeros(4), torch.ones(4)
    torch.manual_seed(3)
    loss, reconstruction, kl = negative_elbo(model, unit, labels, prior, 0.5, samples=5)
    torch.manual_seed(3)
    loc, scale = model.posterior(unit, labels)
    draws = torch.distributions.Normal(loc, scale).rsample((5,))
    reference = sum((labels[i] - model.decoder(torch.cat([unit[i], draws[s]]))[0]) ** 2
                    for s in range(5) for i in range(7)) / 5
    assert float(reconstruction.detach()) == pytest.approx(float(reference.detach()),
                                                           rel=1e-5)
    assert float(loss.detach()) == pytest.approx(float((reference + 0.5 * kl).detach()),
                                                 rel=1e-5)


# --- MPTS's acquisition --------------------------------------------------------------------------


class KnownScore(MPTSPrinciple):
    """MPTS whose score is a known function of the identifiers: the amplitude."""

    def scores(self, params: torch.Tensor) -> torch.Tensor:
        return params[:, 0].float()


def test_ucb_picks_the_top_tasks_of_its_score():
    torch.manual_seed(4)
    mean, std = torch.rand(40), torch.rand(40)
    scores = ucb_scores(mean, std, 1.0, 3.0)
    assert torch.equal(scores, mean + 3.0 * std)
    picked = set(top_b(scores, 8).tolist())
    assert picked == set(torch.argsort(scores, descending=True)[:8].tolist())
    assert min(scores[list(picked)]) > max(scores[[i for i in range(40) if i not in picked]])


def test_mpts_proposes_the_top_of_its_pseudo_batch():
    """propose(B) draws B̂ = ceil(ratio·B) p0 candidates and keeps the B best by the score; with a
    random fraction, the best B − floor(f·B) and the first of the others in draw order."""
    p0 = BoxUniform(SPACE)
    principle = KnownScore(p0, MptsOptions(candidate_ratio=2.5))
    torch.manual_seed(5)
    tasks = principle.propose(8)
    torch.manual_seed(5)
    pool = p0.sample(20)["params"]
    best = pool[torch.argsort(pool[:, 0], descending=True)[:8]]
    assert torch.equal(tasks["params"], best)
    assert torch.equal(tasks["log_prob"], p0.log_prob(best).float())
    mixed = mixed_selection(pool[:, 0], 8, 0.5)
    assert mixed[:4].tolist() == torch.argsort(pool[:, 0], descending=True)[:4].tolist()
    assert mixed[4:].tolist() == [i for i in range(20) if i not in mixed[:4].tolist()][:4]


def test_mpts_scores_are_the_moments_of_the_posterior_predictions():
    """m and σ are the mean and standard deviation over z samples: a posterior squeezed to a
    point leaves σ ≈ 0 and m the prediction at that point."""
    torch.manual_seed(6)
    model = RiskPredictiveModel(2)
    unit = torch.rand(30, 2)
    loc = torch.randn(10)
    mean, std = predictive_moments(model, unit, loc, torch.full((10,), 1e-7), 20)
    assert float(std.max()) < 1e-5
    with torch.no_grad():
        assert torch.allclose(mean, model.predict(unit, loc.unsqueeze(0))[0], atol=1e-5)
    _, wide = predictive_moments(model, unit, loc, torch.ones(10), 20)
    assert float(wide.mean()) > 100 * float(std.mean())


# --- PDTS's acquisition --------------------------------------------------------------------------


def reference_greedy(risks: torch.Tensor, points: torch.Tensor, b: int, gamma: float) -> list:
    """Borodin et al.'s greedy, one candidate and one distance at a time."""
    weight = 2 * gamma / (b * (b - 1)) if b > 1 else 0.0
    chosen = []
    for _ in range(b):
        gains = {u: 0.5 * float(risks[u]) + weight * sum(float((points[u] - points[v]).norm())
                                                         for v in chosen)
                 for u in range(len(risks)) if u not in chosen}
        chosen.append(max(gains, key=lambda u: (gains[u], -u)))
    return chosen


@pytest.mark.parametrize("gamma", [0.0, 0.5, 3.0])
def test_greedy_subset_equals_the_per_candidate_reference(gamma):
    torch.manual_seed(7)
    risks, points = torch.rand(30, dtype=torch.float64), torch.rand(30, 2, dtype=torch.float64)
    batched = greedy_diverse_subset(risks, points, 6, gamma)
    assert batched.tolist() == reference_greedy(risks, points, 6, gamma)


@pytest.mark.parametrize("seed", range(5))
def test_greedy_subset_is_within_half_of_the_best_subset(seed):
    """The 2-approximation of max-sum diversification with a modular, non-negative risk term,
    checked against every subset of a small pool."""
    torch.manual_seed(seed)
    risks, points = torch.rand(10, dtype=torch.float64), torch.rand(10, 2, dtype=torch.float64)
    gamma = 2.0
    greedy = greedy_diverse_subset(risks, points, 4, gamma)
    value = float(subset_objective(risks[greedy], points[greedy], gamma))
    best = max(float(subset_objective(risks[list(s)], points[list(s)], gamma))
               for s in itertools.combinations(range(10), 4))
    assert best / 2 <= value <= best + 1e-12


def test_mean_pairwise_distance():
    points = torch.tensor([[0.0, 0.0], [3.0, 4.0], [0.0, 4.0]])
    assert float(mean_pairwise_distance(points)) == pytest.approx((5 + 4 + 3) / 3)
    assert float(mean_pairwise_distance(points[:1])) == 0.0


def test_diversity_spreads_the_picks_the_top_b_rule_concentrates():
    """Proposition 3.3 and its remedy: on a unimodal predicted risk, the top-B picks of a growing
    pseudo-batch shrink around the peak, while the diverse subset stays spread out."""
    torch.manual_seed(8)
    spread = {}
    for pool in (64, 4096):
        params = BoxUniform(SPACE).sample_params(pool)
        risks = landscape(params) / 4  # predicted losses in (0.25, 1.25]
        for gamma in (0.0, 1.0):
            picked = greedy_diverse_subset(risks, params, 16, gamma)
            spread[pool, gamma] = float(mean_pairwise_distance(params[picked]))
    assert spread[4096, 0.0] < 0.3 * spread[64, 0.0]
    assert spread[4096, 1.0] > 4 * spread[4096, 0.0]
    assert spread[4096, 1.0] > spread[64, 0.0]


def test_pdts_posterior_sample_is_one_draw_for_all_candidates():
    """Eq. (12a)–(12b): the risks are the predictions under one z from the posterior."""
    torch.manual_seed(9)
    model = RiskPredictiveModel(2, latent=3)
    unit, loc, scale = torch.rand(50, 2), torch.randn(3), torch.rand(3) + 0.1
    torch.manual_seed(10)
    risks = posterior_sample_risks(model, unit, loc, scale)
    torch.manual_seed(10)
    z = torch.distributions.Normal(loc, scale).sample((1,))
    with torch.no_grad():
        assert torch.equal(risks, model.predict(unit, z)[0])


def test_pdts_distance_option_measures_in_identifiers_or_the_unit_box():
    """The sinusoid box is 4.9 × π: identifier distances favour spreading the amplitude, unit
    distances weigh both identifiers alike."""
    torch.manual_seed(11)
    params = BoxUniform(SPACE).sample_params(512)
    flat = torch.zeros(512, dtype=torch.float64)  # no risk signal: diversity alone decides
    by_identifier = params[greedy_diverse_subset(flat, params, 8, 1.0)]
    by_unit = params[greedy_diverse_subset(flat, SPACE.to_unit(params), 8, 1.0)]
    identifier_spread = by_identifier.std(0) / torch.tensor([4.9, math.pi], dtype=torch.float64)
    unit_spread = by_unit.std(0) / torch.tensor([4.9, math.pi], dtype=torch.float64)
    assert float(identifier_spread[0] / identifier_spread[1]) > float(unit_spread[0]
                                                                      / unit_spread[1])


# --- the principles ------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["mpts", "pdts"])
def test_principle_protocol_warmup_and_resume(kind):
    """A risk principle (uniform weights, no extra evaluation); warm-up proposals are p0 draws;
    a principle restored from a state dict continues bit-identically."""
    p0 = BoxUniform(SPACE)
    make = ((lambda **o: MPTSPrinciple(p0, MptsOptions(**o))) if kind == "mpts" else
            (lambda **o: PDTSPrinciple(p0, PdtsOptions(**o))))
    principle = make(warmup=2)
    assert isinstance(principle, RiskPrinciple)
    assert principle.update_every == 1 and not principle.needs_next_losses
    assert torch.equal(principle.weights(torch.rand(5)), torch.full((5,), 0.2))
    torch.manual_seed(12)
    first = principle.propose(6)
    torch.manual_seed(12)
    assert torch.equal(first["params"], p0.sample(6)["params"])
    torch.manual_seed(13)
    train_on_landscape(principle, 4, batch=6)
    copy = make(warmup=2)
    copy.load_state_dict(deepcopy(principle.state_dict()))  # its tensors alias the live ones
    rng = torch.get_rng_state()
    ours = train_on_landscape(principle, 3, batch=6)
    torch.set_rng_state(rng)
    theirs = train_on_landscape(copy, 3, batch=6)
    assert all(torch.equal(a, b) for a, b in zip(ours, theirs))
    for name, value in principle.state_dict().items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, copy.state_dict()[name]), name


@pytest.mark.parametrize("kind", ["mpts", "pdts"])
def test_non_finite_predictions_and_losses_diverge_and_leave_the_model(kind):
    principle = (MPTSPrinciple(BoxUniform(SPACE)) if kind == "mpts"
                 else PDTSPrinciple(BoxUniform(SPACE)))
    torch.manual_seed(14)
    tasks = principle.propose(4)
    before = {k: v.clone() for k, v in principle.state_dict().items()
              if isinstance(v, torch.Tensor)}
    with pytest.raises(TrainingDiverged, match="non-finite task losses"):
        principle.update(tasks, torch.tensor([1.0, math.nan, 2.0, 3.0]))
    with pytest.raises(ValueError, match="one loss per task"):
        principle.update(tasks, torch.ones(3))
    for name, value in before.items():
        assert torch.equal(value, principle.state_dict()[name]), name
    with torch.no_grad():
        principle.model.decoder[-1].bias.fill_(math.inf)
    with pytest.raises(TrainingDiverged, match=f"risk.{kind}: the risk model predicted a "
                                               "non-finite risk"):
        principle.propose(4)


@pytest.mark.parametrize(("options", "key", "value"), [
    (MptsOptions, "candidate_ratio", 0.5),
    (PdtsOptions, "candidate_ratio", 0.99),
    (MptsOptions, "random_fraction", 1.0),
    (MptsOptions, "score_samples", 1),
    (PdtsOptions, "distance", "manhattan"),
    (PdtsOptions, "diversity", -1.0),
])
def test_options_refuse_bad_values(options, key, value):
    with pytest.raises(ConfigError) as error:
        options(**{key: value})
    assert error.value.key == f"{options.section}.{key}"


@pytest.mark.parametrize("kind", ["mpts", "pdts"])
def test_builder_reads_the_section(kind):
    cfg = compose_train(f"method={kind}_maml", f"risk.{kind}.candidate_ratio=3.0",
                        f"risk.{kind}.hidden=7")
    principle = players_of(cfg).principle
    assert principle.candidate_ratio == 3.0 and principle.pool_size(25) == 75
    assert principle.model.decoder[0].out_features == 7


@pytest.mark.parametrize("override,words", [
    ("risk.mpts.gama_std=5", "did you mean 'risk.mpts.gamma_std'?"),
    ("risk.pdts.candidate_ratio=0.5", "must be >= 1 (the candidate pool holds at least the batch)"),
    ("risk.mpts.gamma_std=inf", "must be a finite number"),
    ("risk.pdts.kl_weight=nan", "must be a finite number"),
])
def test_bad_options_get_one_line_and_exit_code_2(tmp_path, capsys, override, words):
    """An unknown key, a pool smaller than the batch or a non-finite value, through the CLI."""
    kind, key = override.split(".")[1], override.split("=")[0]
    run_dir = tmp_path / "run"
    code = train([f"method={kind}_maml", override, f"hydra.run.dir={run_dir}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and f"'{key}'" in err[0] and words in err[0], err
    assert not run_dir.exists()


@pytest.mark.parametrize("kind", ["mpts", "pdts"])
def test_a_non_finite_predicted_risk_stops_the_run_at_its_last_checkpoint(
    tmp_path, monkeypatch, capsys, kind
):
    """The model's predictions for iteration 4's candidates are non-finite: the run stops with
    one line (exit code 1) naming iteration 3's checkpoint, which the run resumes from."""
    from conftest import SMALL_RUN

    module, name = (mpts, "predictive_moments") if kind == "mpts" else (
        pdts, "posterior_sample_risks")
    score, calls = getattr(module, name), []

    def non_finite_at_4(*args, **kwargs):
        calls.append(1)
        out = score(*args, **kwargs)
        return (tuple(torch.full_like(o, math.inf) for o in out) if isinstance(out, tuple)
                else torch.full_like(out, math.nan)) if len(calls) == 4 else out

    run_dir = tmp_path / "run"
    args = [*SMALL_RUN, f"method={kind}_maml", "trainer.meta_batch=4", "eval.n_tasks=4"]
    with monkeypatch.context() as patch:
        patch.setattr(module, name, non_finite_at_4)
        code = train([*args, f"hydra.run.dir={run_dir}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1, err
    assert f"risk.{kind}: the risk model predicted a non-finite risk" in err[0]
    assert "checkpoint-000000000003 is kept" in err[0]
    assert train([f"resume={run_dir}"]) == 0 and (run_dir / "eval.json").is_file()


# --- outside the trainer -------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["mpts", "pdts"])
def test_principle_sampler_is_the_principle_with_a_task_samplers_verbs(kind):
    """sample(n) / update(tasks, losses) on a loop of our own give the tasks and statistics of
    propose / update, identifiers alone accepted in place of the task TensorDict."""
    def run(drive):
        torch.manual_seed(15)
        principle = (MPTSPrinciple(BoxUniform(SPACE), MptsOptions(**FAST)) if kind == "mpts"
                     else PDTSPrinciple(BoxUniform(SPACE), PdtsOptions(**FAST)))
        return drive(principle), principle

    def through_sampler(principle):
        sampler, out = PrincipleSampler(principle), []
        for _ in range(5):
            tasks = sampler.sample(8)
            out.append((tasks["params"], sampler.update(tasks["params"],
                                                        landscape(tasks["params"]))))
        with pytest.raises(ConfigError, match="'n' = 0"):
            sampler.sample(0)
        with pytest.raises(TrainingDiverged):
            sampler.update(tasks, torch.full((8,), math.inf))
        return out

    def directly(principle):
        out = []
        for _ in range(5):
            tasks = principle.propose(8)
            out.append((tasks["params"], principle.update(tasks, landscape(tasks["params"]))))
        return out

    (ours, _), (theirs, _) = run(through_sampler), run(directly)
    for (a, stats_a), (b, stats_b) in zip(ours, theirs):
        assert torch.equal(a, b) and stats_a == stats_b


def test_principle_sampler_updates_every_update_every_calls():
    """A principle with ``update_every = 2`` (here the flow adversary) is updated on every
    second call, as in the trainer."""
    from armeta_rl.adversary import FlowAdversary
    from armeta_rl.risk.adversarial import AdversarialPrinciple, ArOptions

    torch.manual_seed(16)
    principle = AdversarialPrinciple(FlowAdversary(SPACE, BoxUniform(SPACE)),
                                     ArOptions(update_every=2))
    sampler = PrincipleSampler(principle)
    tasks = sampler.sample(8)
    before = [p.clone() for p in principle.parameters()]
    assert sampler.update(tasks, landscape(tasks["params"])) == {}
    assert all(torch.equal(a, b) for a, b in zip(before, principle.parameters()))
    assert "adversary/objective" in sampler.update(tasks, landscape(tasks["params"]))
    assert not all(torch.equal(a, b) for a, b in zip(before, principle.parameters()))


@pytest.mark.parametrize("kind", ["mpts", "pdts"])
def test_maml_trpo_trains_with_a_risk_predictive_principle(tmp_path, kind):
    """On a meta-RL benchmark the learner is MAML-TRPO; the risk model learns from the
    returns-based losses of each step's tasks."""
    from armeta_rl.job import Job
    from armeta_rl.trainers.training import run_training
    from conftest import SMALL_RUN

    cfg = compose_train(*SMALL_RUN, "benchmark=point_nav", f"method={kind}_maml",
                        "trainer.iterations=2", "trainer.meta_batch=3", "eval.n_tasks=3",
                        "benchmark.collector.episodes=2", "benchmark.collector.max_steps=10",
                        "logger=csv")
    config = validate(cfg)
    report = run_training(Job(config, tmp_path))
    assert report["metric"] == "return" and report["method"] == f"{kind}_maml"
    assert (tmp_path / "logs" / "scalars" / "risk" / "pcc.csv").is_file()
    assert moved_players(config, tmp_path) == {"leader": True, "principle": True}


def test_the_two_reconstruction_terms_differ_by_the_variance_over_z():
    """E_z[(ℓ − ℓ̂)²] = (ℓ − E_z[ℓ̂])² + Var_z[ℓ̂], task by task: the authors' term
    (``mean_prediction``) is ours less the predictions' spread over the z samples."""
    torch.manual_seed(4)
    labels, predictions = torch.randn(6, dtype=torch.float64), torch.randn(9, 6,
                                                                           dtype=torch.float64)
    expected = reconstruction_error(labels, predictions, "expected")
    averaged = reconstruction_error(labels, predictions, "mean_prediction")
    spread = predictions.var(0, unbiased=False).sum()
    assert float(expected) == pytest.approx(float(averaged + spread), rel=1e-12)
    assert float(averaged) == pytest.approx(float((labels - predictions.mean(0)).square().sum()))


def test_label_scale_divides_the_losses_before_standardizing():
    losses = torch.tensor([1.0, 3.0, 8.0])
    scaled = MPTSPrinciple(BoxUniform(SPACE), MptsOptions(label_scale=10.0))
    assert torch.allclose(scaled.labels(losses), losses / 10)
    standardized = MPTSPrinciple(BoxUniform(SPACE), MptsOptions(label_scale=10.0,
                                                                standardize=True))
    plain = MPTSPrinciple(BoxUniform(SPACE), MptsOptions(standardize=True))
    assert torch.allclose(standardized.labels(losses), plain.labels(losses), atol=1e-6)


def test_with_the_authors_reconstruction_term_mpts_still_runs_the_worst_tasks():
    torch.manual_seed(0)
    principle = MPTSPrinciple(BoxUniform(SPACE), MptsOptions(
        **FAST, reconstruction="mean_prediction"))
    proposals = train_on_landscape(principle, 300)
    p0_share = float(near_peak(BoxUniform(SPACE).sample_params(100_000)).double().mean())
    assert float(near_peak(torch.cat(proposals[-100:])).double().mean()) > 1.6 * p0_share
