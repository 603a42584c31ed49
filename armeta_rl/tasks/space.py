"""The box of task identifiers (paper, appendix table "A Summary of Benchmarks")."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from armeta_rl.errors import ConfigError

FLOAT32_MAX = float(torch.finfo(torch.float32).max)


def _float32(value: float) -> float:
    return float(torch.tensor(value, dtype=torch.float32))


@dataclass(frozen=True)
class TaskSpace:
    """A named, axis-aligned box ``[low, high]`` of task identifiers τ ∈ R^d.

    Args:
        names: one name per identifier, e.g. ``("amplitude", "phase")``.
        low: lower corner of the box.
        high: upper corner of the box; every ``high[i]`` must exceed ``low[i]``, also once both
            are rounded to float32 (the dtype of the identifiers tasks carry).

    Examples:
        >>> import torch
        >>> from armeta_rl.tasks import TaskSpace
        >>> space = TaskSpace(["amplitude", "phase"], low=[0.1, 0.0], high=[5.0, 3.1416])
        >>> space.dim
        2
        >>> space.contains(torch.tensor([[1.0, 1.0], [6.0, 1.0]]))
        tensor([ True, False])
    """

    names: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]

    def __init__(self, names: Sequence[str], low: Sequence[float], high: Sequence[float]) -> None:
        names, low, high = (
            tuple(str(n) for n in names),
            tuple(map(float, low)),
            tuple(map(float, high)),
        )
        if not names:
            raise ConfigError("benchmark.space.names", list(names), "needs at least one identifier")
        for key, value in (("low", low), ("high", high)):
            if len(value) != len(names):
                raise ConfigError(
                    f"benchmark.space.{key}",
                    list(value),
                    f"needs {len(names)} values, one per name",
                )
            if not all(abs(v) <= FLOAT32_MAX for v in value):
                raise ConfigError(f"benchmark.space.{key}", list(value),
                                  f"must be finite float32 numbers, |value| <= {FLOAT32_MAX:.3g} "
                                  "(tasks carry their identifiers in float32)")
        for name, lo, hi in zip(names, low, high):
            if not _float32(lo) < _float32(hi):
                raise ConfigError(
                    "benchmark.space.low",
                    list(low),
                    f"must be < high for every identifier ({name}: {lo} >= {hi})",
                )
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)

    @property
    def dim(self) -> int:
        """Number of identifiers d."""
        return len(self.names)

    def bounds(
        self, dtype: torch.dtype | None = None, device: torch.device | None = None
    ) -> tuple[Tensor, Tensor]:
        """``(low, high)`` as tensors of shape ``[d]``."""
        kwargs = {"dtype": dtype or torch.get_default_dtype(), "device": device}
        return torch.tensor(self.low, **kwargs), torch.tensor(self.high, **kwargs)

    @property
    def log_volume(self) -> float:
        """ln of the box volume; the entropy of the uniform distribution on the box."""
        return sum(math.log(hi - lo) for lo, hi in zip(self.low, self.high))

    def to_unit(self, params: Tensor) -> Tensor:
        """Affine map of the box onto ``[0, 1]^d`` (its Jacobian is constant)."""
        low, high = self.bounds(params.dtype, params.device)
        return (params - low) / (high - low)

    def quarter(self, params: Tensor) -> Tensor:
        """The quarter of the box ``[n]`` (long, 0 to 3) of each row of ``params``: for a 1-D
        box its four equal intervals in order; for d ≥ 2 the 2×2 cells of the halves of the
        first two identifiers, 2·(upper half of the first) + (upper half of the second). Four
        parts of equal volume, so p0 uniform puts 1/4 on each, and where a learner does worst
        and where an adversary puts its mass can be read on the same cells.

        Examples:
            >>> import torch
            >>> from armeta_rl.tasks import TaskSpace
            >>> TaskSpace(["v"], low=[0.0], high=[2.0]).quarter(torch.tensor([[0.1], [1.9]]))
            tensor([0, 3])
            >>> square = TaskSpace(["x", "y"], low=[-1.0, -1.0], high=[1.0, 1.0])
            >>> square.quarter(torch.tensor([[-0.5, 0.5], [0.5, -0.5]]))
            tensor([1, 2])
        """
        unit = self.to_unit(params.to(torch.float64))
        if self.dim == 1:
            return (4 * unit[..., 0]).floor().long().clamp(0, 3)
        return 2 * (unit[..., 0] >= 0.5).long() + (unit[..., 1] >= 0.5).long()

    def contains(self, params: Tensor) -> Tensor:
        """Boolean ``[n]``: whether each row of ``params`` lies in the closed box."""
        low, high = self.bounds(params.dtype, params.device)
        return ((params >= low) & (params <= high)).all(-1)

    def grid(
        self, points_per_axis: int, dtype: torch.dtype = torch.float64
    ) -> tuple[Tensor, float]:
        """Midpoints of a regular grid over the box and the area of one cell (for quadrature)."""
        low, high = self.bounds(dtype)
        width = (high - low) / points_per_axis
        axes = [
            lo + w * (torch.arange(points_per_axis, dtype=dtype) + 0.5) for lo, w in zip(low, width)
        ]
        mesh = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, self.dim)
        return mesh, float(width.prod())

