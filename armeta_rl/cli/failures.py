"""How ``armeta-train`` and ``armeta-eval`` end: the one table of their exit codes and the line
each prints (:func:`failure`), and the wrapper that ends a Hydra job with them
(:func:`report_errors`)."""

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
    if isinstance(error, (MemoryError, RuntimeError, OSError, SystemError)) and out_of_memory(
            error):
        return 2, f"error: {OUT_OF_MEMORY}"
    if isinstance(error, OSError):
        return 1, "error: " + f"{error.strerror or error}: {error.filename or ''}".rstrip(": ")
    return None


OUT_OF_MEMORY = ("out of memory: this process may not allocate what the run needs (a memory "
                 "limit, or sizes too large for this machine): smaller sizes, or more memory")


def out_of_memory(error: BaseException) -> bool:
    """Whether ``error`` is an allocation that failed (Python's ``MemoryError``, torch's CPU or
    CUDA allocator, or the ``SystemError`` CPython raises when an import runs out of memory
    under this process's address-space limit)."""
    if isinstance(error, OSError):
        return error.errno == errno.ENOMEM
    if isinstance(error, SystemError):
        return resource.getrlimit(resource.RLIMIT_AS)[0] != resource.RLIM_INFINITY
    text = str(error)
    return isinstance(error, MemoryError) or "can't allocate memory" in text or (
        "out of memory" in text.lower())


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
