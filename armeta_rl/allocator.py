"""glibc's malloc keeps freed blocks for reuse (``trainer.keep_freed_memory``, on by default).

A meta-iteration allocates and frees the same large tensors again and again: the per-task
parameters of batched MAML and, in MAML-TRPO, the activations and gradients of every KL
Hessian-vector product of conjugate gradient. glibc serves blocks above its mmap threshold with
fresh pages from the kernel and returns heap memory above its trim threshold to the kernel, so each
such block pays page faults for zero-filled memory again. Raising both thresholds keeps the blocks
in the heap. It changes where memory comes from, never a value: seeded runs are identical with
and without it. A process-wide setting is the caller's business, so only the ``armeta-train``
entry point calls this, when its run's config says so.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def keep_freed_memory(mmap_threshold: int = 64 << 20, trim_threshold: int = 256 << 20) -> bool:
    """Raise glibc's mmap and trim thresholds (bytes) with ``mallopt``; returns whether both were
    set (``False`` off Linux or without glibc, where nothing changes)."""
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold)) and bool(
        mallopt(_M_TRIM_THRESHOLD, trim_threshold)
    )
