"""Shift suites: named, fixed task distributions on a benchmark's identifier box that no
adversary chose (docs/meta-rl.md), declared in ``configs/shift_suites/<suite>.yaml`` and named
by a benchmark's ``benchmark.shift_suite``.

A suite file maps names to specifications, each one of three kinds:

* ``{kind: box, low: [...], high: [...]}``: uniform on a sub-box (a corner, an edge strip);
* ``{kind: cells, grid: [n_1, ..., n_d], cells: [[i_1, ..., i_d], ...]}``: uniform on the union of
  cells of a regular grid over the box (e.g. the hardest cells of a reference learner, or the
  cells along the box's rim);
* ``{kind: beta, a: [...], b: [...]}``: independent Beta(a_i, b_i) on each axis, mapped onto the
  box (a skewed p0).

Every shift is checked against the box it is scored on: a shift outside it, an unknown kind or
a malformed entry is refused with :class:`~armeta_rl.errors.ConfigError`, and so is a name the
suite does not have.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from torch import Tensor

from armeta_rl.config_files import config_files, group_choices
from armeta_rl.errors import ConfigError
from armeta_rl.tasks.distributions import TaskDistribution
from armeta_rl.tasks.space import TaskSpace

SHIFT_KINDS = ("box", "cells", "beta")
SUITE_KEY = "benchmark.shift_suite"
ALL = "all"


class UniformOnBoxes(TaskDistribution):
    """Uniform on a union of disjoint boxes inside the identifier box (each ``(low, high)``):
    ln p(τ) = −ln(total volume) inside one of them, −∞ elsewhere."""

    def __init__(self, space: TaskSpace, boxes: Sequence[tuple[Sequence[float], Sequence[float]]]
                 ) -> None:
        super().__init__(space)
        lows = torch.tensor([list(low) for low, _ in boxes], dtype=torch.float64)
        highs = torch.tensor([list(high) for _, high in boxes], dtype=torch.float64)
        volumes = (highs - lows).prod(-1)
        self.register_buffer("box_low", lows, persistent=False)
        self.register_buffer("box_high", highs, persistent=False)
        self.register_buffer("box_weight", volumes / volumes.sum(), persistent=False)
        self.register_buffer("log_density", -volumes.sum().log(), persistent=False)

    def sample_params(self, n: int) -> Tensor:
        which = torch.multinomial(self.box_weight, n, replacement=True)
        unit = torch.rand(n, self.space.dim, dtype=torch.float64, device=self.box_low.device)
        low, high = self.box_low[which], self.box_high[which]
        return low + unit * (high - low)

    def log_prob(self, params: Tensor) -> Tensor:
        params = params.to(torch.float64)
        inside = ((params.unsqueeze(-2) >= self.box_low) & (params.unsqueeze(-2) <= self.box_high)
                  ).all(-1).any(-1)
        return torch.where(inside, self.log_density, -math.inf)

    def entropy(self, n: int = 0) -> Tensor:
        return -self.log_density


class BetaOnBox(TaskDistribution):
    """Independent Beta(a_i, b_i) on each identifier, mapped affinely onto the box: ln p(τ) =
    Σ_i [ln Beta(u_i; a_i, b_i) − ln(high_i − low_i)], u the box mapped onto [0, 1]^d."""

    def __init__(self, space: TaskSpace, a: Sequence[float], b: Sequence[float]) -> None:
        super().__init__(space)
        self.register_buffer("a", torch.tensor(list(a), dtype=torch.float64), persistent=False)
        self.register_buffer("b", torch.tensor(list(b), dtype=torch.float64), persistent=False)

    def _beta(self) -> torch.distributions.Beta:
        return torch.distributions.Beta(self.a, self.b, validate_args=False)

    def sample_params(self, n: int) -> Tensor:
        unit = self._beta().sample((n,))
        return self.low + unit * (self.high - self.low)

    def log_prob(self, params: Tensor) -> Tensor:
        params = params.to(torch.float64)
        unit = ((params - self.low) / (self.high - self.low)).clamp(0.0, 1.0)
        log_density = (self._beta().log_prob(unit) - (self.high - self.low).log()).sum(-1)
        return torch.where(self._inside(params), log_density, -math.inf)


def shift_seed(seed: int, name: str) -> int:
    """The seed a shift's evaluation tasks are drawn under: the evaluation seed offset by the
    shift's name (CRC-32), so a shift gets the same tasks in every report, whichever other
    distributions the report scores."""
    return (seed + 2 + zlib.crc32(name.encode())) % 2**64


def suite_names() -> list[str]:
    """The suites in ``configs/shift_suites/``."""
    return group_choices("shift_suites")


def suite_path(suite: str) -> Path:
    """The file of suite ``suite``: ``configs/shift_suites/<suite>.yaml``."""
    return config_files() / "shift_suites" / f"{suite}.yaml"


def load_suite(suite: str | None, benchmark: str) -> dict[str, dict[str, Any]]:
    """The specifications of suite ``suite`` (``configs/shift_suites/<suite>.yaml``) by name;
    :class:`ConfigError` when the benchmark has none or the file does not exist."""
    if suite is None:
        raise ConfigError("shifts", ALL, f"benchmark {benchmark} has no shift suite "
                          f"({SUITE_KEY} is null); suites: {', '.join(suite_names())}")
    if not suite_path(suite).is_file():
        raise ConfigError(SUITE_KEY, suite, f"allowed: {', '.join(suite_names())}")
    specs = OmegaConf.to_container(OmegaConf.load(suite_path(suite)), resolve=True)
    if not isinstance(specs, dict) or not specs:
        raise ConfigError(SUITE_KEY, suite, "its file must map shift names to specifications")
    return specs


def select_shifts(specs: dict[str, Any], chosen: str | Sequence[str]) -> list[str]:
    """The names ``chosen`` asks for (``"all"``: every one, in the suite's order);
    :class:`ConfigError` for a name the suite does not have."""
    if chosen == ALL:
        return list(specs)
    names = [chosen] if isinstance(chosen, str) else list(chosen)
    if not names:
        raise ConfigError("shifts", names, f"must be {ALL} or a non-empty list of shift names")
    for name in names:
        if name not in specs:
            raise ConfigError("shifts", name, f"allowed: {ALL}, {', '.join(specs)}")
    return names


def make_shift(space: TaskSpace, name: str, spec: Any) -> TaskDistribution:
    """The distribution a suite's specification describes on ``space``; :class:`ConfigError`
    (naming ``shifts.<name>``) for an unknown kind, a malformed entry or a shift outside the
    box."""
    key = f"shifts.{name}"
    if not isinstance(spec, dict) or spec.get("kind") not in SHIFT_KINDS:
        raise ConfigError(f"{key}.kind", spec.get("kind") if isinstance(spec, dict) else spec,
                          f"allowed: {', '.join(SHIFT_KINDS)}")
    kind, d = spec["kind"], space.dim
    fields = {"box": {"low", "high"}, "cells": {"grid", "cells"}, "beta": {"a", "b"}}[kind]
    if set(spec) != fields | {"kind"}:
        raise ConfigError(key, spec,
                          f"a {kind} shift has the keys: kind, {', '.join(sorted(fields))}")
    for field in fields - {"cells"}:
        if not _numbers(spec[field], d):
            raise ConfigError(f"{key}.{field}", spec[field], f"needs {d} numbers, one per "
                              f"identifier ({', '.join(space.names)})")
    if kind == "box":
        low, high = [float(v) for v in spec["low"]], [float(v) for v in spec["high"]]
        if not all(lo < hi for lo, hi in zip(low, high)):
            raise ConfigError(f"{key}.low", low, "must be < high for every identifier")
        _check_inside(space, key, low, high)
        return UniformOnBoxes(space, [(low, high)])
    if kind == "beta":
        if not all(v > 0 for v in [*spec["a"], *spec["b"]]):
            raise ConfigError(key, spec, "a and b must be > 0")
        return BetaOnBox(space, spec["a"], spec["b"])
    return UniformOnBoxes(space, _cells(space, key, spec["grid"], spec["cells"]))


def _numbers(values: Any, d: int) -> bool:
    return isinstance(values, list) and len(values) == d and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        for v in values)


def _check_inside(space: TaskSpace, key: str, low: Sequence[float],
                  high: Sequence[float]) -> None:
    for name, lo, hi, box_lo, box_hi in zip(space.names, low, high, space.low, space.high):
        if lo < box_lo or hi > box_hi:
            raise ConfigError(key, {"low": list(low), "high": list(high)},
                              f"lies outside the box: {name} must stay in [{box_lo:g}, "
                              f"{box_hi:g}]")


def _cells(space: TaskSpace, key: str, grid: Any, cells: Any
           ) -> list[tuple[list[float], list[float]]]:
    """The boxes of the grid cells ``cells`` (index lists) of a ``grid`` over the box."""
    d = space.dim
    if not (isinstance(grid, list) and len(grid) == d
            and all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in grid)):
        raise ConfigError(f"{key}.grid", grid, f"needs {d} integers >= 1 (cells per axis)")
    if not isinstance(cells, list) or not cells:
        raise ConfigError(f"{key}.cells", cells, "needs a non-empty list of cell indices")
    boxes, seen = [], set()
    for cell in cells:
        if not (isinstance(cell, list) and len(cell) == d and all(
                isinstance(i, int) and not isinstance(i, bool) for i in cell)):
            raise ConfigError(f"{key}.cells", cell, f"a cell is {d} integer indices")
        if not all(0 <= i < n for i, n in zip(cell, grid)) or tuple(cell) in seen:
            raise ConfigError(f"{key}.cells", cell, f"lies outside the grid {grid} or repeats "
                              "a cell: every index i_k must be in [0, n_k) and every cell once")
        seen.add(tuple(cell))
        width = [(hi - lo) / n for lo, hi, n in zip(space.low, space.high, grid)]
        low = [lo + i * w for lo, i, w in zip(space.low, cell, width)]
        boxes.append((low, [lo + w for lo, w in zip(low, width)]))
    return boxes


def suite_shifts(space: TaskSpace, suite: str | None, benchmark: str,
                 chosen: str | Sequence[str]) -> dict[str, TaskDistribution]:
    """The shifts ``chosen`` (``"all"`` or names) of ``suite`` on ``space``, by name, each checked
    (:func:`make_shift`)."""
    specs = load_suite(suite, benchmark)
    return {name: make_shift(space, name, specs[name]) for name in select_shifts(specs, chosen)}
