"""glibc's malloc keeps freed blocks for reuse (``trainer.keep_freed_memory``, on by default).

A meta-iteration allocates and frees the same large tensors again and again: the per-task
parameters of batched MAML and, in MAML-TRPO, the activations and gradients of every KL
Hessian-vector product of conjugate gradient. glibc serves blocks above its mmap threshold with
fresh pages from the kernel and returns free memory at the top of its heap to the kernel once it
exceeds the trim threshold, so each such block pays page faults for zero-filled memory again.
Raising the mmap threshold keeps the blocks in the heap, and turning trimming off keeps the heap:
every iteration frees and reaches again the same peak, so any finite trim threshold below what it
frees at once hands that memory back at every free and faults it in again at the next allocation
(at MAML's protocol on HalfCheetah, each curvature product frees more than 256 MiB at once). The
process holds on to the heap of its largest iteration, which the next iteration needs again. It
changes where memory comes from, never a value: seeded runs are identical with and without it. A
process-wide setting is the caller's business, so only the ``armeta-train`` entry point calls
this, when its run's config says so.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import sys
from collections.abc import Callable

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

NEVER_TRIM = -1
"""The trim threshold that turns trimming off (``mallopt(3)``)."""


@functools.cache
def _mallopt() -> Callable[[int, int], int] | None:
    """glibc's ``mallopt``, looked up once (``None`` off Linux or without glibc)."""
    if not sys.platform.startswith("linux"):
        return None
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return None
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt


def keep_freed_memory(mmap_threshold: int = 64 << 20, trim_threshold: int = NEVER_TRIM) -> bool:
    """Raise glibc's mmap threshold and set its trim threshold (bytes; :data:`NEVER_TRIM`, the
    default, turns trimming off) with ``mallopt``; returns whether both were set (``False`` off
    Linux or without glibc, where nothing changes)."""
    mallopt = _mallopt()
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold)) and bool(
        mallopt(_M_TRIM_THRESHOLD, trim_threshold)
    )
