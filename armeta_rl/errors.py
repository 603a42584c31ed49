"""Errors a user can act on: a bad configuration value, a broken checkpoint, a run directory that
cannot be written or is in use, a diverged run."""

from __future__ import annotations

from typing import Any

from hydra.errors import CompactHydraException


class ConfigError(ValueError):
    """A configuration value is not allowed.

    The message names the config key, the value given and what is allowed, so the CLI can print it
    as one line and exit with code 2.
    """

    def __init__(self, key: str, value: Any, allowed: str) -> None:
        self.key, self.value, self.allowed = key, value, allowed
        super().__init__(f"config key '{key}' = {value!r}: {allowed}")

    def __reduce__(self) -> tuple[type, tuple[str, Any, str]]:
        """Pickle by the constructor's arguments, so that the error crosses process boundaries
        (a Ray actor's or a worker process's env raising it)."""
        return type(self), (self.key, self.value, self.allowed)


class CheckpointBroken(ConfigError):
    """The run directory a key points at has no intact checkpoint to load (exit code 2)."""


class RunDirectoryError(RuntimeError):
    """The run directory cannot be written (a full disk, a read-only file system) or another
    process holds it; the checkpoints already there are kept."""


class TrainingDiverged(RuntimeError):
    """A loss or a flow output stopped being finite or left ``trainer.max_loss``; the last good
    checkpoint, if any, is kept."""


class IdentifierError(ConfigError):
    """Task identifiers handed to an env are not allowed (misplaced key, wrong width, a value
    outside the env's range).

    The message names the TensorDict key, the value given and what is allowed, on one line. It is
    a :class:`ConfigError` (so a ``ValueError``) because in a training run the identifiers come
    from the configured box: the CLI reports it as one line with exit code 2.
    """

    def __init__(self, key: str, value: Any, allowed: str) -> None:
        self.key, self.value, self.allowed = key, value, allowed
        ValueError.__init__(self, f"tensordict key '{key}' = {value}: {allowed}")


class RunStopped(RuntimeError):
    """A run stopped before it finished because the process was asked to (a preemption signal,
    Ctrl-C); the message names the checkpoint kept and the resume command, and ``code`` is the
    exit code (:mod:`armeta_rl.preemption`)."""

    def __init__(self, message: str, code: int) -> None:
        self.code = code
        super().__init__(message)

    def __reduce__(self) -> tuple[type, tuple[str, int]]:
        return type(self), (str(self), self.code)


class RunNotStarted(RunStopped):
    """A run that never started: its process had been asked to stop before (a later job of a
    sweep worker that received ``SIGTERM``); the same command starts it."""


class CollectionFailed(RuntimeError):
    """A collection worker died or stopped answering; the run stops, keeping its last checkpoint."""


class JobFailed(CompactHydraException):
    """A job of a ``run_list`` sweep stopped with a user error, already printed as one line with
    its exit ``code``. Raised in place of ``SystemExit`` so that Hydra records the job as failed
    and the launcher runs the others (a ``SystemExit`` in a joblib worker aborts the jobs running
    beside it, losing their work); the sweeper exits with the code once every job ran. A job
    that never started (:class:`RunNotStarted`) printed nothing (``started`` false)."""

    def __init__(self, code: int, started: bool = True) -> None:
        self.code, self.started = code, started
        super().__init__(f"a job of the sweep stopped with exit code {code}; its error is above")

    def __reduce__(self) -> tuple[type, tuple[int, bool]]:
        """Pickle by the exit code and whether the job started, so that the error comes back
        from a worker process."""
        return type(self), (self.code, self.started)
