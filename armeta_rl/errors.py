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


class TrainingDiverged(RuntimeError):
    """A loss or a flow output stopped being finite; the last good checkpoint is kept."""


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
