"""How ``armeta-train`` and ``armeta-eval`` end: the one table of their exit codes and the line
each prints (:func:`failure`), and the wrapper that ends a Hydra job with them
(:func:`report_errors`), and the floor of the address space they start under
(:func:`address_space_refusal`)."""

from __future__ import annotations

import errno
import resource  # here, not where it is needed: under a memory limit it cannot be loaded then
import sys
from collections.abc import Callable

from omegaconf import DictConfig

from armeta_rl.errors import (
    CollectionFailed,
    ConfigError,
    JobFailed,
    RunDirectoryError,
    RunNotStarted,
    RunStopped,
    TrainingDiverged,
)
from armeta_rl.preemption import EXIT_INTERRUPTED


class Refused(ValueError):
    """A command refused with one line (``message``) and an exit code."""

    def __init__(self, message: str, code: int = 2) -> None:
        super().__init__(message)
        self.code = code


def report_errors(prog: str, task: Callable[[DictConfig], None]) -> Callable[[DictConfig], None]:
    """Run ``task`` turning the package's user errors into one line and their exit code
    (:func:`failure`). A job of a ``run_list`` sweep (``armeta-reproduce``) raises
    :class:`~armeta_rl.errors.JobFailed` with that code instead of exiting, so that the jobs
    beside it run on; the sweeper exits with the code once all ran."""

    def wrapped(cfg: DictConfig) -> None:
        try:
            task(cfg)
        except Exception as error:
            status = failure(error)
            if status is None:
                raise
            code, line = status
            in_sweep = _in_run_list_sweep()
            started = not isinstance(error, RunNotStarted)
            if started or not in_sweep:  # a sweep's progress says which jobs did not start
                print(f"{prog}: {line}", file=sys.stderr)
            if in_sweep:
                raise JobFailed(code, started) from None
            sys.exit(code)

    return wrapped


def failure(error: BaseException) -> tuple[int, str] | None:
    """The exit code of ``error`` and the line that says it: the one table of the codes of
    ``armeta-train`` and ``armeta-eval``. 2: a refused value or command, or an allocation that
    failed; 1: a run that diverged, lost a collection worker or could not write; a stopped run's
    own code (:mod:`armeta_rl.preemption`). ``None`` for any other error: a bug, whose traceback
    is the report."""
    if isinstance(error, (ConfigError, Refused)):
        return getattr(error, "code", 2), f"error: {error}"
    if isinstance(error, RunStopped):  # not an error: a code a requeue acts on
        return error.code, str(error)
    if isinstance(error, (TrainingDiverged, CollectionFailed)):
        return 1, f"error: training stopped: {error}"
    if isinstance(error, RunDirectoryError):
        return 1, f"error: {error}"
    if isinstance(error, KeyboardInterrupt):  # Ctrl-C where no run stops cleanly
        return EXIT_INTERRUPTED, "interrupted (SIGINT)"
    if isinstance(error, (MemoryError, RuntimeError, OSError, SystemError, ImportError,
                          ValueError)) and out_of_memory(error):
        return 2, f"error: {OUT_OF_MEMORY}"
    if isinstance(error, OSError):
        return 1, "error: " + f"{error.strerror or error}: {error.filename or ''}".rstrip(": ")
    return None


OUT_OF_MEMORY = ("out of memory: this process may not allocate what the run needs (a memory "
                 "limit, or sizes too large for this machine): smaller sizes, or more memory")


def out_of_memory(error: BaseException) -> bool:
    """Whether ``error`` is an allocation that failed: Python's ``MemoryError``, torch's CPU or
    CUDA allocator, MuJoCo's, or, under this process's address-space limit, a library the
    loader could not map or an import that ran out of memory (the ``SystemError`` CPython raises
    then)."""
    text = str(error).lower()
    limited = resource.getrlimit(resource.RLIMIT_AS)[0] != resource.RLIM_INFINITY
    if limited and "failed to map segment" in text:
        return True
    if isinstance(error, OSError):
        return error.errno == errno.ENOMEM
    if isinstance(error, SystemError):
        return limited
    return isinstance(error, MemoryError) or any(
        words in text for words in ("can't allocate memory", "could not allocate memory",
                                    "out of memory"))


ADDRESS_SPACE_FLOOR = 1 << 30
"""The smallest address-space limit (``ulimit -v``) the entry points start under. A tiny run
needs about 900 MiB of address space to load torch, NumPy, MuJoCo and Matplotlib; under less a
library's loader fails in ways no handler catches (a C++ ``std::bad_alloc`` that aborts, OpenBLAS
exiting with its own line)."""


def address_space_refusal() -> str | None:
    """The line refusing to start under an address-space limit below
    :data:`ADDRESS_SPACE_FLOOR`; ``None`` without a limit or above it."""
    limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    if limit == resource.RLIM_INFINITY or limit >= ADDRESS_SPACE_FLOOR:
        return None
    return (f"out of memory: this process's address-space limit (ulimit -v) is {limit >> 20} "
            f"MiB, below the {ADDRESS_SPACE_FLOOR >> 20} MiB that loading torch and MuJoCo "
            "needs: raise it, or lift it (ulimit -v unlimited)")


def _in_run_list_sweep() -> bool:
    """Whether this job belongs to a ``hydra/sweeper=run_list`` multirun."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from hydra_plugins.armeta_run_list.run_list_sweeper import RunListSweeperConf

    if not HydraConfig.initialized():
        return False
    hydra_cfg = HydraConfig.get()
    return (hydra_cfg.mode == RunMode.MULTIRUN
            and hydra_cfg.sweeper.get("_target_") == RunListSweeperConf._target_)
