"""Opt-in ``torch.compile`` of the game's hot paths (config keys ``learner.maml.compile``,
``risk.ar.compile`` and, for system identification, ``benchmark.collector.compile``).

A meta-iteration on small tasks is bound by per-op overhead: thousands of small torch ops in the
flow adversary's spline couplings and in the vmapped second-order MAML step, and the physics
steps of a system-identification rollout, one after the other. Compiling fuses them.
It pays on long runs only: the first iterations wait for the compiler (minutes with an empty
cache, much less once torch's on-disk compile cache holds the graphs), and shapes are static, so
each distinct batch shape compiles once. ``python -m benchmarks.timing bench_speed_options``
measures each switch against the eager default (docs/speed-options.md).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import torch

from armeta_rl.errors import ConfigError

F = TypeVar("F", bound=Callable)

COMPILE_KEYS = ("learner.maml.compile", "risk.ar.compile", "benchmark.collector.compile")
"""The config keys that switch compiling on."""

BACKENDS = ("inductor", "aot_eager", "eager")
"""``inductor`` generates fused kernels (the speed-up); ``aot_eager`` and ``eager`` trace the same
graphs without code generation (seconds to compile, for checking that a path compiles)."""


def compile_backend(key: str, value: bool | str | None) -> str | None:
    """The ``torch.compile`` backend a ``compile`` option asks for: ``false``/``null`` → none,
    ``true`` → ``inductor``, or a backend name from :data:`BACKENDS`."""
    if value is None or value is False:
        return None
    if value is True:
        return "inductor"
    if isinstance(value, str) and value in BACKENDS:
        return value
    raise ConfigError(key, value, "allowed: false, true or a backend (" + ", ".join(BACKENDS) + ")")


def maybe_compile(fn: F, backend: str | None) -> F:
    """``fn`` itself without a backend, else ``torch.compile(fn)`` with static shapes."""
    return fn if backend is None else torch.compile(fn, backend=backend, dynamic=False)
