"""What this machine offers a run, and the least a run's sizes ask of it, checked when its config
is validated: before anything is allocated (docs/configuration.md, "Sizes and threads").

A size (``eval.n_tasks``, ``trainer.meta_batch``, ``risk.ar.initial_samples``) is refused when
even a lower bound of the memory it needs exceeds the memory of the device the run computes on:
for a batch of tasks, the activations of one forward pass of the learner's network over every
task's samples, 4 bytes each; for the adversary's p0 sample, its identifiers and log-densities in
float64. The run needs more than that (the inner loop's graph, the collected data), so a size
let through can still be too large; one refused could never run.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

FLOAT32_BYTES, FLOAT64_BYTES = 4, 8
CGROUP_LIMITS = (Path("/sys/fs/cgroup/memory.max"),
                 Path("/sys/fs/cgroup/memory/memory.limit_in_bytes"))


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity mask: a Slurm or container allocation),
    else all of the machine's."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def machine_memory(device: str = "cpu") -> int:
    """Bytes of memory a run on ``device`` computes in: the GPU's for ``cuda[:N]``, else the
    machine's RAM, or the memory limit of this process's cgroup if that is smaller."""
    if device.startswith("cuda"):
        import torch

        index = int(device.split(":")[1]) if ":" in device else torch.cuda.current_device()
        return int(torch.cuda.get_device_properties(index).total_memory)
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for limit in CGROUP_LIMITS:
        try:
            text = limit.read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            total = min(total, int(text))
    return total


SAMPLE_COUNTS = ("n_transitions", "n_support", "n_query", "episodes", "max_steps")
"""A collector's arguments that count its samples per task."""


def sample_counts(collector: Mapping[str, Any], section: str) -> dict[str, int]:
    """The collector's :data:`SAMPLE_COUNTS` it names, as integers; ``section`` names the
    collector (``benchmark.collector``) in the :class:`~armeta_rl.errors.ConfigError` for one
    that is not a whole number (``inf``, ``2.5``, ``"ten"``)."""
    from armeta_rl.errors import ConfigError

    counts = {}
    for name in SAMPLE_COUNTS:
        if name not in collector:
            continue
        value = collector[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                math.isfinite(value) and value == int(value) and value >= 0):
            raise ConfigError(f"{section}.{name}", value, "must be a whole number >= 0")
        counts[name] = int(value)
    return counts


def samples_per_task(collector: Mapping[str, Any], section: str = "benchmark.collector") -> int:
    """The samples a collector gathers per task, from its arguments (:func:`sample_counts`):
    ``n_transitions`` (system identification), ``n_support + n_query`` (regression), or
    ``episodes × max_steps`` (episodes); 1 when it names none."""
    counts = sample_counts(collector, section)
    if "n_transitions" in counts:
        return counts["n_transitions"]
    if "n_support" in counts or "n_query" in counts:
        return counts.get("n_support", 0) + counts.get("n_query", 0)
    if "episodes" in counts and "max_steps" in counts:
        return counts["episodes"] * counts["max_steps"]
    return 1


def hidden_units(section: Any) -> int:
    """The hidden units of a learner's network (the sum of its ``hidden`` / ``hidden_sizes``
    widths): the activations of one sample in one forward pass."""
    fields = section if isinstance(section, Mapping) else vars(section)
    units = 0
    for name, value in fields.items():
        if name.startswith("hidden"):
            units += sum(int(v) for v in value) if isinstance(value, (list, tuple)) else int(value)
    return max(units, 1)


def task_batch_bytes(tasks: int, collector: Mapping[str, Any], units: int,
                     section: str = "benchmark.collector") -> int:
    """The least memory a batch of ``tasks`` tasks needs: one forward pass's activations over
    every task's samples, in float32."""
    return FLOAT32_BYTES * tasks * samples_per_task(collector, section) * units


def spline_layer_parameters(dim: int, bins: int, hidden: int, blocks: int) -> int:
    """At least the parameters of one layer of the spline flow on a ``dim``-dimensional box
    (:class:`~armeta_rl.adversary.flows.SplineBoxFlow`): an unconditional spline of ``3 bins +
    1`` numbers per coordinate in one dimension; in more, a coupling whose residual network
    (``hidden`` units, ``blocks`` blocks of two layers) maps the half it conditions on to every
    spline of the other half, beside unconditional splines of that half."""
    spline = 3 * bins + 1
    if dim == 1:
        return spline
    kept, moved = dim - dim // 2, dim // 2
    network = (kept + 1) * hidden + blocks * 2 * (hidden + 1) * hidden + (hidden + 1) * (
        moved * spline)
    return network + kept * spline


def sample_bytes(samples: int, dim: int) -> int:
    """The least memory ``samples`` identifiers of ``dim`` dimensions need with their
    log-densities, in float64."""
    return FLOAT64_BYTES * samples * (dim + 1)


def size_words(size: int) -> str:
    """``size`` bytes as GiB, TiB, ... with three significant digits."""
    value, unit = size / 2**30, "GiB"
    for bigger in ("TiB", "PiB", "EiB"):
        if value < 1024:
            break
        value, unit = value / 1024, bigger
    return f"{value:.3g} {unit}"
