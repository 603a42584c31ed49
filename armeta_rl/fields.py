"""Config fields: a key's type (the field's annotation), allowed range, the wording of the error
line for a value out of it, and default value, declared once with :func:`key` and its shorthands
(:func:`at_least`, :func:`above`, :func:`inside`, :func:`one_of`, :func:`each`); the strict check
of plain values against a dataclass of such fields; and :class:`Options`, a learner's or a risk
principle's options.

:mod:`armeta_rl.config`'s schema and every learner's and risk principle's options are made of
these fields. This module imports no learner or principle, so their modules can declare their
options here while :mod:`armeta_rl.config` derives the ``learner:`` and ``risk:`` schemas from the
registered ones.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Union

from omegaconf import DictConfig, OmegaConf

from armeta_rl.errors import ConfigError

_MISSING = object()


def key(
    allowed: str = "",
    test: Callable[[Any], bool] | None = None,
    old_runs: Any = _MISSING,
    default: Any = None,
) -> Any:
    """A schema field: ``test`` (on a value of the right type) and ``allowed``, the end of the
    error line when it fails (``must be >= 1``, ``allowed: a, b``); ``old_runs`` is the value a
    run directory saved before the key existed gets when it is loaded (only for keys added after
    runs were saved); ``default`` is the key's value in a composed config, for the keys whose
    values are declared here rather than in ``configs/`` (a learner's or a risk principle's
    options, :func:`defaults`)."""
    metadata = {"allowed": allowed, "test": test, "old_runs": old_runs}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata=metadata)
    return field(default=default, metadata=metadata)


def at_least(low: float, default: Any = None) -> Any:
    return key(f"must be >= {low:g}", lambda v: v >= low, default=default)


def above(low: float, default: Any = None) -> Any:
    return key(f"must be > {low:g}", lambda v: v > low, default=default)


def inside(low: float, high: float, closed: str = "()", default: Any = None) -> Any:
    """In the interval from ``low`` to ``high``; ``closed`` gives its brackets, e.g. ``"(]"``."""
    lo = (lambda v: v >= low) if closed[0] == "[" else (lambda v: v > low)
    hi = (lambda v: v <= high) if closed[1] == "]" else (lambda v: v < high)
    return key(f"must be in {closed[0]}{low:g}, {high:g}{closed[1]}", lambda v: lo(v) and hi(v),
               default=default)


def one_of(*choices: str, default: Any = None) -> Any:
    return key(f"allowed: {', '.join(choices)}", lambda v: v in choices, default=default)


def each(check: Any, nonempty: bool = False, default: Any = None) -> Any:
    """Every element of a list passes ``check`` (a field made by :func:`at_least` and the like);
    with ``nonempty`` the list must have one at least."""
    words, test = check.metadata["allowed"].removeprefix("must be "), check.metadata["test"]
    allowed = f"must be a non-empty list, every element {words}" if nonempty else (
        f"every element must be {words}")
    return key(allowed, lambda v: (len(v) > 0 or not nonempty) and all(test(a) for a in v),
               default=default)


def defaults(options: type) -> dict[str, Any]:
    """The default value of every key of an options dataclass (a learner's ``learner.<name>``
    or a risk principle's ``risk.<name>`` section), as a composed config holds them."""
    return dataclasses.asdict(options())


@dataclass(frozen=True)
class Options:
    """A learner's or a risk principle's options: the keys of its config section ``section``
    (``"learner.maml"``, ``"risk.dr"``), one field each, made with this module's helpers (type,
    range and default value, declared once). The constructor takes them
    (``MAMLLeader(model, collector, MamlOptions(inner_lr=0.05))``) and its builder makes them
    from the section (``MamlOptions(**section(cfg, "learner.maml"))``). They are checked when
    made, so a bad value from Python is refused with the line the CLI prints
    (``config key 'learner.maml.inner_lr' = 0: must be > 0``)."""

    section: ClassVar[str]

    def __post_init__(self) -> None:
        values = {spec.name: getattr(self, spec.name) for spec in dataclasses.fields(self)}
        _check_node(type(self), _plain(values), f"{self.section}.")


def _type_words(hint: Any) -> str:
    """What a value of type ``hint`` is, in words: ``an integer``, ``a list of numbers``, ..."""
    if _optional(hint) is not None:
        return f"{_type_words(_optional(hint))} or null"
    origin = typing.get_origin(hint)
    if origin is list:
        inner = _type_words(typing.get_args(hint)[0]).split(" ", 1)[1]
        return f"a list of {inner}s"
    if origin is dict or dataclasses.is_dataclass(hint):
        return "a group of keys"
    return {bool: "a boolean (true or false)", int: "an integer", float: "a finite number",
            str: "a string"}[hint]


def _optional(hint: Any) -> Any:
    """``X`` for ``X | None``, else ``None``."""
    if typing.get_origin(hint) in (Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return args[0]
    return None


def _conforms(value: Any, hint: Any) -> bool:
    """Whether ``value`` (plain Python) has type ``hint``, strictly (no string is a boolean)."""
    if hint is Any:
        return True
    if _optional(hint) is not None:
        return value is None or _conforms(value, _optional(hint))
    origin = typing.get_origin(hint)
    if origin is list:
        return isinstance(value, list) and all(
            _conforms(v, typing.get_args(hint)[0]) for v in value
        )
    if origin is dict or dataclasses.is_dataclass(hint):
        return isinstance(value, dict)
    if hint is float:
        return (isinstance(value, (int, float)) and not isinstance(value, bool)
                and math.isfinite(value))
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, hint)


def _check_node(schema: type, node: dict, prefix: str) -> None:
    hints = typing.get_type_hints(schema)
    for spec in dataclasses.fields(schema):
        if spec.name not in node:
            continue
        name, value, hint = f"{prefix}{spec.name}", node[spec.name], hints[spec.name]
        if not _conforms(value, hint):
            choices = spec.metadata["allowed"] if spec.metadata["allowed"].startswith(
                "allowed:") else ""
            raise ConfigError(name, value, f"must be {_type_words(hint)}" + (
                f"; {choices}" if choices else ""))
        if value is None:
            continue
        nested = _optional(hint) or hint
        if dataclasses.is_dataclass(nested):
            _check_node(nested, value, f"{name}.")
        test = spec.metadata["test"]
        if test is not None and not test(value):
            raise ConfigError(name, value, spec.metadata["allowed"])


def _plain(values: dict[str, Any]) -> dict[str, Any]:
    """``values`` as a config holds them: a tuple (``hidden=(64, 64)``) is a list."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in values.items()}


def section(cfg: DictConfig, key: str) -> dict[str, Any]:
    """The keys under ``key`` of a composed config as a plain, resolved dict (``{}`` when absent):
    what a builder hands on as arguments (``section(cfg, "learner.anil")``)."""
    node = OmegaConf.select(cfg, key)
    return {} if node is None else OmegaConf.to_container(node, resolve=True)
