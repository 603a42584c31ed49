"""Wall-clock timing shared by the benchmark scripts (run as ``python benchmarks/<name>.py``)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import torch


def wall_times(
    fn: Callable[[], object],
    repeats: int,
    warmup: int = 1,
    clock: Callable[[], float] = time.perf_counter,
) -> list[float]:
    """Seconds taken by each of ``repeats`` calls of ``fn``, after ``warmup`` untimed calls, on
    ``clock`` (wall time; ``time.process_time`` gives this process's CPU time, less sensitive to
    other processes)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = clock()
        fn()
        times.append(clock() - start)
    return times


def reference_product_ms(repeats: int = 50) -> float:
    """Median ms of one ``[16, 190, 128] × [16, 128, 128]`` float32 ``bmm``, the largest product of
    the system-identification MAML step: a yardstick of how fast the machine runs at the moment
    (medians of 1.2–1.7 ms over a benchmark run on the development machine, single turns
    1.1–3.4 ms: it has fast and slow spells), so that tables taken at different times can be
    compared."""
    activations, weights = torch.randn(16, 190, 128), torch.randn(16, 128, 128)
    times = wall_times(lambda: torch.bmm(activations, weights), repeats, warmup=5)
    return 1000 * statistics.median(times)
