"""Initial task distributions p0 on the identifier box (paper, appendix benchmark table).

Every distribution here, and the flow adversary built on top of one, shares one interface:
``sample(n)`` returns a TensorDict ``{"params": [n, d], "log_prob": [n]}`` and ``log_prob(params)``
is the exact, normalized log-density on the box (``-inf`` outside it). Sampling uses torch's global
generator of the device the distribution lives on (``.to(device)``, as any module), so
``torch.manual_seed`` fixes it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDict
from torch import Tensor, nn

from armeta_rl.errors import ConfigError
from armeta_rl.tasks.protocol import TASK_KEY, IdentifierCheck
from armeta_rl.tasks.space import TaskSpace


def entropy_estimate(log_prob: Tensor) -> Tensor:
    """Monte-Carlo entropy H[p] = −E_p[ln p(τ)] from the log-densities ``[n]`` of samples of p: the
    entropy of paper Eq. (12) (Remark "Entropy of the Generated Task Distribution"), estimated
    as in the first line of its proof, Eq. (46)."""
    return -log_prob.mean()


def kl_terms(initial_log_prob: Tensor, log_prob: Tensor) -> Tensor:
    """The terms r − 1 − ln r ``[n]``, r = p(τ)/p0(τ), at samples τ of p0 from the log-densities
    ``[n]`` of p0 and of p there: each is ≥ 0, and since E_{p0}[r] = 1 their mean is an unbiased
    estimate of D_KL[p0 ‖ p] = E_{p0}[−ln r] (Schulman's "k3" estimator), which unlike the mean of
    −ln r cannot come out negative; their spread gives its standard error. Infinite where p
    leaves out part of p0's support."""
    log_ratio = log_prob - initial_log_prob
    return torch.expm1(log_ratio) - log_ratio


def kl_estimate(initial_log_prob: Tensor, log_prob: Tensor) -> Tensor:
    """Monte-Carlo D_KL[p0 ‖ p], the mean of :func:`kl_terms` at samples of p0: the
    distribution shift that the constraint of paper Eq. (4) bounds by δ."""
    return kl_terms(initial_log_prob, log_prob).mean()


class TaskDistribution(nn.Module):
    """Base class: a distribution over the task box with an exact log-density.

    Examples:
        >>> import torch
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> p0 = BoxUniform(TaskSpace(["x"], low=[0.0], high=[2.0]))
        >>> tasks = p0.sample(3)
        >>> tasks["params"].shape, tasks["log_prob"].shape
        (torch.Size([3, 1]), torch.Size([3]))
        >>> p0.log_prob(torch.tensor([[1.0], [3.0]], dtype=torch.float64)).exp()
        tensor([0.5000, 0.0000], dtype=torch.float64)
    """

    def __init__(self, space: TaskSpace) -> None:
        super().__init__()
        self.space = space
        low, high = space.bounds(torch.float64)
        self.register_buffer("low", low, persistent=False)
        self.register_buffer("high", high, persistent=False)
        self._inner_bounds: dict[tuple[torch.dtype, torch.device], tuple[Tensor, Tensor]] = {}

    def sample_params(self, n: int) -> Tensor:
        """``n`` identifiers ``[n, d]`` in float64."""
        raise NotImplementedError

    def log_prob(self, params: Tensor) -> Tensor:
        """Exact log-density ``[n]`` at any ``params [n, d]``; ``-inf`` outside the box."""
        raise NotImplementedError

    def sample_with_log_prob(self, n: int) -> tuple[Tensor, Tensor]:
        """``n`` identifiers and their log-densities, both float64 and detached."""
        params = self.sample_params(n)
        return params, self.log_prob(params)

    def sample(self, n: int) -> TensorDict:
        """``n`` tasks as ``{"params": [n, d], "log_prob": [n]}`` in the default dtype."""
        return self.as_tasks(*self.sample_with_log_prob(n))

    def as_tasks(self, params: Tensor, log_prob: Tensor) -> TensorDict:
        """The TensorDict :meth:`sample` returns for samples ``params [n, d]`` and their
        log-densities ``[n]``, in the default dtype."""
        dtype = torch.get_default_dtype()
        return TensorDict(
            {TASK_KEY: self._cast_inside(params, dtype), "log_prob": log_prob.to(dtype)},
            batch_size=[len(params)],
        )

    def _cast_inside(self, params: Tensor, dtype: torch.dtype) -> Tensor:
        """Round ``params`` to ``dtype`` without leaving the box: a face such as π is not a float32
        number, and a sample on it would round outside (where the density is zero). A value that
        rounds outside lands on the nearest ``dtype`` number inside instead."""
        key = (dtype, self.low.device)
        if key not in self._inner_bounds:
            low, high = self.low.to(dtype), self.high.to(dtype)
            low = torch.where(low.to(torch.float64) < self.low, torch.nextafter(low, high), low)
            high = torch.where(high.to(torch.float64) > self.high, torch.nextafter(high, low), high)
            self._inner_bounds[key] = (low, high)
        return params.to(dtype).clamp(*self._inner_bounds[key])

    def entropy(self, n: int = 4096) -> Tensor:
        """Entropy H[p] = -E_p[ln p(τ)] (Monte Carlo, :func:`entropy_estimate`, unless a subclass
        knows it exactly)."""
        return entropy_estimate(self.log_prob(self.sample_params(n)))

    @torch.no_grad()
    def kl_from(self, initial: TaskDistribution, n: int = 4096) -> tuple[Tensor, Tensor]:
        """Monte-Carlo KL(p0 ‖ p) (:func:`kl_estimate`, paper Eq. (4)) from ``n`` fresh samples of
        ``initial`` (p0), and its standard error: how far p has moved from p0; detached
        scalars."""
        params = initial.sample_params(n)
        terms = kl_terms(initial.log_prob(params), self.log_prob(params))
        return terms.mean(), terms.std() / math.sqrt(n)

    @torch.no_grad()
    def quarter_mass(self, n: int = 4096) -> Tensor:
        """Monte-Carlo mass ``[4]`` (float64, summing to 1) of each quarter of the box
        (:meth:`~armeta_rl.tasks.TaskSpace.quarter`) from ``n`` fresh samples: where p puts its
        tasks, to read against where a learner does worst (p0 uniform: 1/4 each, each within
        about 0.007 at n = 4096)."""
        quarters = self.space.quarter(self.sample_params(n))
        return torch.bincount(quarters.cpu(), minlength=4).to(torch.float64) / n

    def _inside(self, params: Tensor) -> Tensor:
        return ((params >= self.low) & (params <= self.high)).all(-1)


class BoxUniform(TaskDistribution):
    """Uniform distribution on the box: ln p(τ) = -ln vol(box).

    Examples:
        >>> import torch
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> p0 = BoxUniform(TaskSpace(["m", "l"], low=[0.4, 0.4], high=[1.6, 1.6]))
        >>> bool(p0.space.contains(p0.sample_params(100)).all())
        True
        >>> p0.entropy()  # ln of the box's area, 1.2 * 1.2
        tensor(0.3646, dtype=torch.float64)
    """

    def __init__(self, space: TaskSpace) -> None:
        super().__init__(space)
        log_density = torch.tensor(-space.log_volume, dtype=torch.float64)
        self.register_buffer("log_density", log_density, persistent=False)

    def sample_params(self, n: int) -> Tensor:
        unit = torch.rand(n, self.space.dim, dtype=torch.float64, device=self.low.device)
        return self.low + unit * (self.high - self.low)

    def log_prob(self, params: Tensor) -> Tensor:
        return torch.where(self._inside(params.to(torch.float64)), self.log_density, -math.inf)

    def entropy(self, n: int = 0) -> Tensor:
        return torch.tensor(self.space.log_volume, dtype=torch.float64)



class TaskEnvMixin:
    """What every task env of the package tells about its tasks, from class attributes:
    ``identifier_names`` (the order of ``"params"``), ``task_boxes`` (``name: (low, high)``, the
    references' task distribution's support), so that ``TaskSampler`` and ``TaskTransform`` are
    built from the env alone, and the reset contract its resets are checked with
    (:attr:`identifier_check`): the interval every identifier must lie in
    (``identifier_low``, ``identifier_high``, open at the low end with
    ``identifier_open_low``), the other reset keys the env reads (``reset_reads``) and whether
    every full reset must carry the identifiers (``require_identifiers``)."""

    identifier_names: tuple[str, ...] = ()
    task_boxes: dict[str, tuple[float, float]] = {}
    identifier_low: float = -math.inf
    identifier_high: float = math.inf
    identifier_open_low: bool = False
    reset_reads: tuple[str, ...] = ()
    require_identifiers: bool = False

    @property
    def task_space(self) -> TaskSpace:
        """The box of this env's identifiers, in the order of ``"params"``."""
        boxes = self.task_boxes
        return TaskSpace(self.identifier_names, [boxes[n][0] for n in self.identifier_names],
                         [boxes[n][1] for n in self.identifier_names])

    @property
    def p0(self) -> BoxUniform:
        """The references' initial task distribution: uniform on :attr:`task_space`."""
        return BoxUniform(self.task_space)

    @property
    def identifier_check(self) -> IdentifierCheck:
        """The reset contract this env checks its resets with."""
        return IdentifierCheck.uniform(self.identifier_names, self.identifier_low,
                                       self.identifier_high, self.identifier_open_low,
                                       self.require_identifiers, self.reset_reads)


MIN_BOX_MASS = 1e-6
"""The least mass a truncated normal p0 may have along each axis of the box: its inverse-CDF
sampler maps ``u`` into ``[Φ(α), Φ(β)]``, and with less mass than this the float64 CDF keeps
fewer than ten significant digits of the samples (none, once the mass underflows)."""


class TruncatedNormal(TaskDistribution):
    """Diagonal normal N(loc, diag(scale²)) truncated to the box, sampled by inverse CDF.

    ln p(τ) = Σ_i [ln φ((τ_i − μ_i)/σ_i) − ln σ_i − ln(Φ(β_i) − Φ(α_i))] inside the box, with
    α_i, β_i the standardized box edges.

    Examples:
        >>> import torch
        >>> from armeta_rl.tasks import TaskSpace, TruncatedNormal
        >>> space = TaskSpace(["amplitude"], low=[0.1], high=[5.0])
        >>> p0 = TruncatedNormal(space, loc=[1.0], scale=[2.0])
        >>> bool(space.contains(p0.sample_params(100)).all())
        True
        >>> float(p0.log_prob(torch.tensor([[6.0]])))  # outside the box
        -inf
    """

    def __init__(self, space: TaskSpace, loc: Sequence[float], scale: Sequence[float]) -> None:
        super().__init__(space)
        if len(loc) != space.dim:
            raise ConfigError("benchmark.initial.loc", list(loc), f"needs {space.dim} values")
        if len(scale) != space.dim or not all(s > 0 for s in scale):
            raise ConfigError(
                "benchmark.initial.scale", list(scale), f"needs {space.dim} values > 0"
            )
        self.register_buffer("loc", torch.tensor(loc, dtype=torch.float64), persistent=False)
        self.register_buffer("scale", torch.tensor(scale, dtype=torch.float64), persistent=False)
        self.register_buffer(
            "cdf_low", torch.special.ndtr((self.low - self.loc) / self.scale), persistent=False
        )
        self.register_buffer(
            "cdf_high", torch.special.ndtr((self.high - self.loc) / self.scale), persistent=False
        )
        mass = self.cdf_high - self.cdf_low
        if not bool((mass >= MIN_BOX_MASS).all()):
            axis = int(mass.argmin())
            raise ConfigError(
                "benchmark.initial.loc", list(loc),
                f"N(loc, scale²) puts {float(mass[axis]):.3g} of its mass on "
                f"[{space.low[axis]:g}, {space.high[axis]:g}] along {space.names[axis]}: "
                f"allowed: at least {MIN_BOX_MASS:g} on every axis of the box (centre p0 in "
                "the box, or widen benchmark.initial.scale)")

    def sample_params(self, n: int) -> Tensor:
        u = torch.rand(n, self.space.dim, dtype=torch.float64, device=self.low.device)
        z = torch.special.ndtri(self.cdf_low + u * (self.cdf_high - self.cdf_low))
        return (self.loc + self.scale * z).clamp(self.low, self.high)

    def log_prob(self, params: Tensor) -> Tensor:
        params = params.to(torch.float64)
        z = (params - self.loc) / self.scale
        log_density = -0.5 * z**2 - 0.5 * math.log(2 * math.pi) - self.scale.log()
        log_mass = (self.cdf_high - self.cdf_low).log()
        total = (log_density - log_mass).sum(-1)
        return torch.where(self._inside(params), total, -math.inf)


def make_initial(
    space: TaskSpace,
    kind: str,
    loc: Sequence[float] | None = None,
    scale: Sequence[float] | None = None,
) -> TaskDistribution:
    """Build p0 from a config: ``kind`` is ``uniform`` or ``normal`` (truncated to the box).

    Examples:
        >>> import torch
        >>> from armeta_rl.tasks import TaskSpace, make_initial
        >>> space = TaskSpace(["x"], low=[0.0], high=[1.0])
        >>> middle = torch.tensor([[0.5]], dtype=torch.float64)
        >>> make_initial(space, "uniform").log_prob(middle).exp()  # 1 / the box's length
        tensor([1.], dtype=torch.float64)
        >>> normal = make_initial(space, "normal", loc=[0.5], scale=[0.2])
        >>> normal.log_prob(middle).exp()  # 1 / (0.2 √(2π)), over the mass in the box, 0.9876
        tensor([2.0198], dtype=torch.float64)
    """
    if kind == "uniform":
        return BoxUniform(space)
    if kind == "normal":
        if loc is None or scale is None:
            raise ConfigError("benchmark.initial", kind, "'normal' needs 'loc' and 'scale'")
        return TruncatedNormal(space, loc, scale)
    raise ConfigError("benchmark.initial.kind", kind, "allowed: uniform, normal")
