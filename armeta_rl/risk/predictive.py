"""The risk predictive model of MPTS and PDTS, its streaming variational inference, and the loop
both principles share: draw a pseudo-batch of candidates from p0, score it with the model, keep
``B`` tasks, learn from their losses.

MPTS (Wang et al. 2025, "Model Predictive Task Sampling for Efficient and Robust Adaptation",
arXiv 2501.11039) treats the history of training batches H_t = {(τ_{t,i}, ℓ_{t,i})}_{i=1..B} as
a sequence generated from latent variables z_t (the generative model restated as Eq. (4) of the
PDTS paper, Qu et al. 2025): p(ℓ | τ, z_t) is a decoder p_ψ, and q_φ(z_t | H_t) an encoder that
mean-pools the batch. Both are trained online, one batch per iteration, by maximizing

    G_ELBO(ψ, φ) = E_{q_φ(z_t|H_t)}[Σ_i ln p_ψ(ℓ_{t,i} | τ_{t,i}, z_t)]
                   − β·D_KL[q_φ(z_t | H_t) ‖ q_φ̄(z_t | H_{t−1})]           (PDTS Eq. (5))

where the prior q_φ̄(z | H_{t−1}) is the previous iteration's posterior, fixed (streaming
variational inference). The prediction for any task is then E_{q_φ(z_t|H_t)}[p_ψ(ℓ | τ, z_t)],
estimated with samples of z_t. MPTS and PDTS differ only in how they score and select a subset of
the candidates (:mod:`armeta_rl.risk.mpts`, :mod:`armeta_rl.risk.pdts`).

Both papers' code uses a deterministic decoder (its output is the predicted loss; the squared error
is −ln p_ψ up to a constant and a scale, a Gaussian of fixed variance), sizes of 10 for every
layer, and a posterior scale floored at 0.1. Here the model reads the identifiers mapped to the
unit box (a fixed affine map of τ, so the same model on any benchmark's box);
docs/risk-predictive.md maps every equation to its function.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn
from torch.distributions import Normal, kl_divergence

from armeta_rl.errors import ConfigError, TrainingDiverged
from armeta_rl.fields import Section, above, at_least, key, one_of
from armeta_rl.risk.erm import uniform_weights
from armeta_rl.risk.tail import exact_ceil
from armeta_rl.tasks.distributions import TaskDistribution
from armeta_rl.tasks.protocol import TASK_KEY

MIN_SCALE = 0.1
"""The floor of the posterior's standard deviation, σ_z = 0.1 + 0.9·sigmoid(·) (both papers'
code): it keeps q_φ(z | H) from collapsing onto a point, so the KL term and the sampled
predictions stay finite."""


RECONSTRUCTIONS = ("expected", "mean_prediction")
"""The reconstruction terms of Eq. (5) (:func:`reconstruction_error`)."""
LABELS = {"loss": "loss", "last_step": "last_step_loss"}
"""A ``label`` option → the per-task output of the leader's step it reads
(:attr:`~armeta_rl.risk.base.RiskPrinciple.label`)."""


@dataclass(frozen=True)
class PredictiveOptions(Section):
    """The keys MPTS's and PDTS's sections share: the pseudo-batch and the risk model's online
    training. Each principle's options give ``candidate_ratio`` its own default.

    Defaults are both papers' sinusoid settings (the MPTS repository's sinusoid code, which PDTS's
    extends); their meta-RL and domain-randomization code uses lr 0.005, 10 steps, β 1e-4 on a mean
    over tasks, one ELBO sample, standardized labels and 50 warm-up iterations (the RL benchmark
    configs set these).

    Attributes:
        candidate_ratio: B̂ / B, the pseudo-batch drawn from p0 per task kept (≥ 1: the pool
            is ``ceil(ratio · B)`` tasks, never fewer than the batch).
        lr: Adam's learning rate for ψ and φ.
        steps: K, the gradient steps on G_ELBO per iteration (each on that iteration's batch).
        kl_weight: β of Eq. (5).
        elbo_samples: the z samples of the Monte-Carlo estimate of Eq. (5)'s expectation.
        hidden: width of every hidden layer and of the pooled representation r.
        latent: dimension of z.
        standardize: train on the batch's losses standardized to mean 0 and standard deviation 1
            (the papers' RL code) rather than on the losses themselves (their sinusoid code).
        warmup: iterations whose tasks come straight from p0 while the model starts learning.
        reconstruction: Eq. (5)'s reconstruction term: ``"expected"``, the expected squared
            error over z, E_q[Σ_i (ℓ_i − ℓ̂_ψ(τ_i, z))²] (ours: the ELBO of a Gaussian decoder),
            or ``"mean_prediction"``, the squared error of the prediction averaged over z,
            Σ_i (ℓ_i − E_q[ℓ̂_ψ(τ_i, z)])² (the authors' code), which lacks the expected term's
            Var_z[ℓ̂] and so lets q_φ keep a wider posterior.
        label_scale: the losses are divided by it before anything else (the authors' sinusoid
            code divides them by k = 10, which weighs their KL term about 100 times more).
        label: what a task's label is in meta-RL: ``"loss"``, its loss, −(the mean return of
            its adapted episodes), as the learner and the evaluation read it; or
            ``"last_step"``, −(the forward reward at the last step of each adapted episode),
            averaged, the MPTS authors' meta-RL label (an env that reports
            ``"reward_forward"``: the locomotion families).
    """

    candidate_ratio: float = key()  # each principle's options: candidate_ratio(default)
    lr: float = above(0, default=5.0e-4)
    steps: int = at_least(1, default=1)
    kl_weight: float = key("must be >= 0", lambda v: v >= 0, default=1.0)
    elbo_samples: int = at_least(1, default=20)
    hidden: int = at_least(1, default=10)
    latent: int = at_least(1, default=10)
    standardize: bool = key(default=False)
    warmup: int = at_least(0, default=0)
    reconstruction: str = one_of(*RECONSTRUCTIONS, default="expected")
    label_scale: float = above(0, default=1.0)
    label: str = one_of(*LABELS, default="loss")


def candidate_ratio(default: float) -> Any:
    """The ``candidate_ratio`` field, B̂ / B ≥ 1, with a principle's default."""
    return key("must be >= 1 (the candidate pool holds at least the batch)", lambda v: v >= 1,
               default=default)


class RiskPredictiveModel(nn.Module):
    """The risk learner: q_φ(z | H) (encoder, mean pooling, Gaussian head) and p_ψ(ℓ | τ, z)
    (decoder), both on identifiers in the unit box.

    Args:
        dim: the identifiers' dimension d.
        hidden: width of every hidden layer and of the representation r.
        latent: dimension of z.
    """

    def __init__(self, dim: int, hidden: int = 10, latent: int = 10) -> None:
        super().__init__()
        self.latent = latent
        self.encoder = nn.Sequential(nn.Linear(dim + 1, hidden), nn.ReLU(),
                                     nn.Linear(hidden, hidden), nn.ReLU(),
                                     nn.Linear(hidden, hidden))
        self.head = nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(),
                                  nn.Linear(hidden, 2 * latent))
        self.decoder = nn.Sequential(nn.Linear(dim + latent, hidden), nn.ReLU(),
                                     nn.Linear(hidden, hidden), nn.ReLU(),
                                     nn.Linear(hidden, hidden), nn.ReLU(),
                                     nn.Linear(hidden, 1))

    def posterior(self, unit: Tensor, labels: Tensor) -> tuple[Tensor, Tensor]:
        """q_φ(z | H) for a batch H of identifiers ``[B, d]`` (unit box) and losses ``[B]``: the
        mean ``[latent]`` and standard deviation ``[latent]`` of a diagonal Gaussian, from the mean
        of the per-task representations r_i = h_φ(τ_i, ℓ_i) (permutation invariant)."""
        pairs = torch.cat([unit, labels.unsqueeze(-1)], -1)
        loc, raw_scale = self.head(self.encoder(pairs).mean(0)).split(self.latent, -1)
        return loc, MIN_SCALE + (1 - MIN_SCALE) * torch.sigmoid(raw_scale)

    def predict(self, unit: Tensor, z: Tensor) -> Tensor:
        """p_ψ(ℓ | τ, z): the predicted loss ``[S, N]`` of ``N`` identifiers ``[N, d]`` (unit box)
        under each of ``S`` latent samples ``[S, latent]``, in one batched pass."""
        inputs = torch.cat([unit.expand(len(z), *unit.shape),
                            z.unsqueeze(1).expand(len(z), len(unit), z.shape[-1])], -1)
        return self.decoder(inputs).squeeze(-1)


def sample_latent(loc: Tensor, scale: Tensor, samples: int) -> Tensor:
    """``samples`` draws ``[S, latent]`` of z ~ N(loc, diag scale²), reparameterized (the
    gradient of Eq. (5) flows to φ through them)."""
    return Normal(loc, scale).rsample((samples,))


def reconstruction_error(labels: Tensor, predictions: Tensor, kind: str = "expected") -> Tensor:
    """The reconstruction term of PDTS Eq. (5) from losses ``[B]`` and predictions ``[S, B]``
    under ``S`` samples of z: ``"expected"``, E_q[Σ_i (ℓ_i − ℓ̂_ψ(τ_i, z))²] (the ELBO's own
    term for a Gaussian decoder of fixed variance), or ``"mean_prediction"``,
    Σ_i (ℓ_i − E_q[ℓ̂_ψ(τ_i, z)])² (the papers' code). They differ by Σ_i Var_z[ℓ̂_ψ(τ_i, z)]."""
    if kind == "mean_prediction":
        return (labels - predictions.mean(0)).square().sum(-1)
    return (labels - predictions).square().sum(-1).mean(0)


def negative_elbo(
    model: RiskPredictiveModel,
    unit: Tensor,
    labels: Tensor,
    prior: tuple[Tensor, Tensor],
    kl_weight: float,
    samples: int,
    reconstruction: str = "expected",
) -> tuple[Tensor, Tensor, Tensor]:
    """−G_ELBO(ψ, φ) of PDTS Eq. (5) on one batch H_t (identifiers ``[B, d]`` in the unit box,
    losses ``[B]``) under the fixed prior ``(loc, scale)`` = q_φ̄(z | H_{t−1}); returns it with
    its two terms, the reconstruction error of ``reconstruction``'s kind
    (:func:`reconstruction_error`, Monte Carlo over ``samples`` z) and the KL."""
    loc, scale = model.posterior(unit, labels)
    predictions = model.predict(unit, sample_latent(loc, scale, samples))
    error = reconstruction_error(labels, predictions, reconstruction)
    kl = kl_divergence(Normal(loc, scale), Normal(*prior)).sum(-1)
    return error + kl_weight * kl, error, kl


def standardized(losses: Tensor) -> Tensor:
    """(ℓ − mean) / (std + 1e-8) over a batch (the papers' RL code's labels); a batch of one
    task is centred only."""
    centred = losses - losses.mean()
    if losses.numel() < 2:
        return centred
    return centred / (losses.std() + 1e-8)


def pearson(x: Tensor, y: Tensor) -> Tensor:
    """Pearson correlation of two vectors (0 when either is constant): how well the model's
    predictions rank a batch's losses, the diagnostic both papers report."""
    x, y = x - x.mean(), y - y.mean()
    norm = x.norm() * y.norm()
    return (x * y).sum() / norm if norm > 0 else torch.zeros((), dtype=x.dtype, device=x.device)


def check_scores(scores: Tensor, section: str) -> Tensor:
    """``scores`` if every one is finite; else :class:`TrainingDiverged` naming the principle."""
    if not torch.isfinite(scores).all():
        bad = int((~torch.isfinite(scores)).sum())
        raise TrainingDiverged(f"{section}: the risk model predicted a non-finite risk for {bad} "
                               f"of {scores.numel()} candidate tasks")
    return scores


def task_params(tasks: TensorDictBase | Tensor) -> Tensor:
    """The identifiers ``[K, d]`` of ``tasks`` (a task TensorDict or the identifiers)."""
    return tasks[TASK_KEY] if isinstance(tasks, TensorDictBase) else tasks


def checked_losses(losses: Tensor, tasks: int, who: str) -> Tensor:
    """``losses`` as a detached tensor, if it holds one finite loss for each of ``tasks`` tasks.

    Raises:
        ValueError: losses that are not one per task.
        TrainingDiverged: a non-finite loss (``who`` names the principle or sampler).
    """
    losses = torch.as_tensor(losses).detach()
    if losses.shape != (tasks,):
        raise ValueError(f"'losses' has shape {tuple(losses.shape)}: one loss per task, "
                         f"shape ({tasks},)")
    if not torch.isfinite(losses).all():
        raise TrainingDiverged(f"{who}: non-finite task losses {losses.tolist()}")
    return losses


def check_batch_size(name: str, n: Any) -> int:
    """``n`` if it is an integer ≥ 1, else a :class:`ConfigError` naming ``name``."""
    if isinstance(n, bool) or not (isinstance(n, int) and n >= 1):
        raise ConfigError(name, n, "must be an integer >= 1")
    return n


class PredictivePrinciple(nn.Module):
    """The loop MPTS and PDTS share (PDTS Algorithms 1 and 3): tasks from a scored pseudo-batch
    of p0, equal weights, and the risk model's streaming update on each step's own losses.

    ``needs_next_losses`` is ``False``: the model learns from the losses of the step's tasks at
    θ_t, which the leader has just computed (both papers train it on the batch's adaptation
    losses before the meta-update, so the follower costs no extra evaluation). Subclasses define
    :meth:`select`, the acquisition. ``state_dict()`` holds the model, the stored posterior
    q(z | H_t) (the next update's prior and the next proposal's belief), the update count and,
    as ``_extra_state``, Adam's state.

    Args:
        initial: p0, where every candidate comes from.
        options: the shared keys (:class:`PredictiveOptions`) of the principle's section.
    """

    update_every = 1
    needs_next_losses = False

    def __init__(self, initial: TaskDistribution, options: PredictiveOptions) -> None:
        super().__init__()
        self.initial, self.section = initial, options.section
        self.candidate_ratio = float(options.candidate_ratio)
        self.steps, self.kl_weight = options.steps, float(options.kl_weight)
        self.elbo_samples, self.standardize = options.elbo_samples, options.standardize
        self.warmup = options.warmup
        self.reconstruction, self.label_scale = options.reconstruction, float(options.label_scale)
        self.label = LABELS[options.label]
        self.model = RiskPredictiveModel(initial.space.dim, options.hidden, options.latent)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=options.lr)
        self.register_buffer("posterior_loc", torch.zeros(options.latent))
        self.register_buffer("posterior_scale", torch.ones(options.latent))
        self.register_buffer("updates", torch.zeros((), dtype=torch.long))

    def unit(self, params: Tensor) -> Tensor:
        """Identifiers ``[N, d]`` mapped to the unit box, in the model's dtype and device."""
        weight = self.model.decoder[0].weight
        return self.initial.space.to_unit(params.to(torch.float64)).to(weight)

    def pool_size(self, n: int) -> int:
        """B̂ = ``ceil(candidate_ratio · n)``, the pseudo-batch for a batch of ``n`` (≥ n)."""
        return exact_ceil(self.candidate_ratio * n)

    @torch.no_grad()
    def propose(self, n: int) -> TensorDict:
        """``n`` tasks: during the warm-up ``n`` draws of p0; then ``select`` keeps ``n`` of a
        pseudo-batch of B̂ p0 draws. Their ``log_prob`` is p0's (the candidates' density)."""
        check_batch_size(f"{self.section}.batch", n)
        if int(self.updates) < self.warmup:
            return self.initial.sample(n)
        candidates = self.initial.sample(self.pool_size(n))
        return candidates[self.select(candidates[TASK_KEY], n)]

    def select(self, params: Tensor, n: int) -> Tensor:
        """Indices ``[n]`` of the candidates ``params [B̂, d]`` to train on."""
        raise NotImplementedError

    def weights(self, losses: Tensor, tasks: TensorDict | None = None) -> Tensor:
        """Uniform weights 1/B: the leader minimizes the plain average over the selected tasks
        (both papers' meta-update)."""
        return uniform_weights(losses)

    def labels(self, losses: Tensor) -> Tensor:
        """The model's training targets: the losses divided by ``label_scale``, then
        standardized (``standardize``)."""
        scaled = losses / self.label_scale if self.label_scale != 1.0 else losses
        return standardized(scaled) if self.standardize else scaled

    def update(self, tasks: TensorDictBase | Tensor, losses: Tensor) -> dict[str, float]:
        """K Adam steps on −G_ELBO (:func:`negative_elbo`) for H_t = (``tasks``, ``losses``)
        with the stored posterior as the fixed prior, then q_φ(z | H_t) stored as the new one.

        Logs ``risk/elbo`` (G_ELBO of the last step), ``risk/reconstruction``, ``risk/kl``,
        ``risk/pcc``: the Pearson correlation of the losses with the model's predictions for
        these tasks before the update (at the posterior mean, drawing no random numbers), and
        ``risk/spread``: the batch's mean pairwise distance in the unit box (about 0.52 for a
        uniform batch in 2-D; lower when the selection concentrates).

        Raises:
            ValueError: losses that are not one per task.
            TrainingDiverged: non-finite losses, ELBO or new posterior; the model, its optimizer
                and the stored posterior are left as they were.
        """
        params = task_params(tasks)
        losses = checked_losses(losses, len(params), self.section)
        unit = self.unit(params)
        labels = self.labels(losses.to(unit))
        prior = (self.posterior_loc.clone(), self.posterior_scale.clone())
        with torch.no_grad():
            predicted = self.model.predict(unit, prior[0].unsqueeze(0))[0]
        backup = copy.deepcopy((self.model.state_dict(), self.optimizer.state_dict()))
        for _ in range(self.steps):
            loss, reconstruction, kl = negative_elbo(self.model, unit, labels, prior,
                                                     self.kl_weight, self.elbo_samples,
                                                     self.reconstruction)
            if not torch.isfinite(loss):
                self._restore(backup)
                raise TrainingDiverged(f"{self.section}: the risk model's ELBO is not finite")
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
        with torch.no_grad():
            loc, scale = self.model.posterior(unit, labels)
        if not (torch.isfinite(loc).all() and torch.isfinite(scale).all()):
            self._restore(backup)
            raise TrainingDiverged(f"{self.section}: the risk model's posterior is not finite")
        self.optimizer.zero_grad(set_to_none=True)
        self.posterior_loc.copy_(loc)
        self.posterior_scale.copy_(scale)
        self.updates += 1
        return {
            "risk/elbo": -float(loss.detach()),
            "risk/reconstruction": float(reconstruction.detach()),
            "risk/kl": float(kl.detach()),
            "risk/pcc": float(pearson(predicted, labels)),
            "risk/spread": float(torch.pdist(unit).mean()) if len(unit) > 1 else 0.0,
        }

    def _restore(self, backup: tuple[dict[str, Any], dict[str, Any]]) -> None:
        self.model.load_state_dict(backup[0])
        self.optimizer.load_state_dict(backup[1])
        self.optimizer.zero_grad(set_to_none=True)

    def get_extra_state(self) -> dict[str, Any]:
        """Adam's state, stored in ``state_dict()["_extra_state"]``."""
        return {"optimizer": self.optimizer.state_dict()}

    def set_extra_state(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`get_extra_state` returned."""
        self.optimizer.load_state_dict(state["optimizer"])

