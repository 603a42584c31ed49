"""Errors a user can act on: a bad configuration value, a diverged run."""

from __future__ import annotations

from typing import Any


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


class TrainingDiverged(RuntimeError):
    """A loss or a flow output stopped being finite; the last good checkpoint is kept."""


class CollectionFailed(RuntimeError):
    """A collection worker died or stopped answering; the run stops, keeping its last checkpoint."""
