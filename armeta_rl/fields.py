"""Config sections as dataclasses: each key one field, with its default and, where it has one,
its allowed range; OmegaConf checks the types, :class:`Section` the ranges.

A learner's, a risk principle's or the run's own section (``learner.maml``, ``risk.ar``,
``trainer``) is a dataclass of fields made with :func:`key` or a shorthand (:func:`at_least`,
:func:`above`, :func:`inside`, :func:`one_of`, :func:`each`). A module registers its section with
:func:`register`, which stores it in Hydra's ConfigStore as a structured config of its group
(``schema/learner/maml``, placed at ``learner.maml``); ``configs/train.yaml`` lists it in its
defaults.
Composing a config then checks every value's type and refuses unknown keys (Hydra), and making
the dataclass (``OmegaConf.to_object``, or a constructor call from Python) checks every range
(:meth:`Section.__post_init__`), and the types of its own values with the same OmegaConf
check (:meth:`Section.typed`): a section made from Python has no other. Errors name the key, the
value and what is allowed (:class:`~armeta_rl.errors.ConfigError`).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import re
import types
import typing
from collections.abc import Callable
from dataclasses import field
from typing import Any, ClassVar, NoReturn

from hydra.core.config_store import ConfigStore
from omegaconf import (
    MISSING,
    DictConfig,
    OmegaConf,
)
from omegaconf.errors import ConfigKeyError, MissingMandatoryValue, OmegaConfBaseException

from armeta_rl.errors import ConfigError


def key(allowed: str = "", test: Callable[[Any], bool] | None = None, default: Any = None) -> Any:
    """A field with ``default`` whose values must pass ``test`` (``None`` passes: it means
    unset); ``allowed`` ends the error line when one does not (``must be >= 1``, ``allowed: a,
    b``)."""
    metadata = {"allowed": allowed, "test": test}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata=metadata)
    return field(default=default, metadata=metadata)


def at_least(low: float, default: Any = None) -> Any:
    return key(f"must be >= {low:g}", lambda v: v >= low, default)


def above(low: float, default: Any = None) -> Any:
    return key(f"must be > {low:g}", lambda v: v > low, default)


def inside(low: float, high: float, closed: str = "()", default: Any = None) -> Any:
    """In the interval from ``low`` to ``high``; ``closed`` gives its brackets, e.g. ``"(]"``."""
    lo = (lambda v: v >= low) if closed[0] == "[" else (lambda v: v > low)
    hi = (lambda v: v <= high) if closed[1] == "]" else (lambda v: v < high)
    return key(f"must be in {closed[0]}{low:g}, {high:g}{closed[1]}", lambda v: lo(v) and hi(v),
               default)


def one_of(*choices: str, default: Any = None) -> Any:
    return key(f"allowed: {', '.join(choices)}", lambda v: v in choices, default)


def each(check: Any, nonempty: bool = False, default: Any = None) -> Any:
    """Every element of a list passes ``check`` (a field made by :func:`at_least` and the like);
    with ``nonempty`` the list must have one at least."""
    words, test = check.metadata["allowed"].removeprefix("must be "), check.metadata["test"]
    allowed = f"must be a non-empty list, every element {words}" if nonempty else (
        f"every element must be {words}")
    return key(allowed, lambda v: (len(v) > 0 or not nonempty) and all(test(a) for a in v),
               default)


class Section:
    """A config section: the dataclass of the keys under ``section`` (``"learner.maml"``,
    ``"trainer"``). Making one checks each value's type and range, so a bad value from Python is
    refused with the line the CLI prints (``config key 'learner.maml.inner_lr' = 0: must be >
    0``); a subclass with rules between its keys extends :meth:`__post_init__`. A learner's or a
    risk principle's constructor takes its section
    (``MAMLLeader(model, collector, MamlOptions(inner_lr=0.05))``)."""

    section: ClassVar[str]

    def __post_init__(self) -> None:
        typed = self.typed()
        for spec in dataclasses.fields(self):  # type: ignore[arg-type]
            value = getattr(self, spec.name)
            if nested(value) or isinstance(value, str) and (
                    value == MISSING or value.startswith("${")):
                continue  # checked when made; a default to be filled or resolved when composed
            if isinstance(value, float) and not math.isfinite(value):
                self.refuse(spec.name, "must be a finite number")
            declared = field_type(type(self), spec.name)
            # typed holds it converted ('0.5' to 0.5): the dataclass kept '0.5'
            if reads_as_boolean(declared, value) or typed[spec.name] != value:
                self.refuse(spec.name, f"must be {type_words(declared)}")
            test = spec.metadata.get("test")
            if value is not None and test is not None and not test(value):
                self.refuse(spec.name, spec.metadata["allowed"])

    def typed(self) -> DictConfig:
        """This section's own values in its structured config, their types checked by OmegaConf
        as a composed config's are; nested sections (:func:`nested`) left out. Read-only, and
        made once per section type and values (:data:`TYPED_KEPT`): a sweep, or a report that
        loads its runs, makes the same sections over and over, and OmegaConf's check costs
        milliseconds each time."""
        own, items = copy.copy(self), []
        for spec in dataclasses.fields(self):  # type: ignore[arg-type]
            if nested(value := getattr(self, spec.name)):
                value = {} if isinstance(value, dict) else MISSING
                object.__setattr__(own, spec.name, value)
            items.append((spec.name, value))
        values = repr(items)
        made = _TYPED.get((type(self), values))
        if made is not None:
            return made
        try:
            made = OmegaConf.structured(own)
        except OmegaConfBaseException as error:
            name = re.match(r"\w*", str(error.full_key)).group()  # hidden[0]: the field hidden
            if not hasattr(self, name):
                raise config_error(error) from None
            self.refuse(name, f"must be {type_words(field_type(type(self), name))}")
        OmegaConf.set_readonly(made, True)
        if len(_TYPED) >= TYPED_KEPT:
            _TYPED.clear()
        _TYPED[type(self), values] = made
        return made

    def refuse(self, name: str, allowed: str) -> NoReturn:
        """Raise the :class:`ConfigError` of this section's key ``name``."""
        where = f"{self.section}.{name}" if self.section else name
        raise ConfigError(where, getattr(self, name), allowed)


TYPED_KEPT = 4096
"""The most typed sections (:meth:`Section.typed`) kept, by section type and the ``repr`` of
its values (which tells ``0.5`` from ``'0.5'`` and ``1`` from ``1.0``); all are dropped when it
is reached."""

_TYPED: dict[tuple[type, str], DictConfig] = {}


def nested(value: Any) -> bool:
    """Whether ``value`` is a :class:`Section` or a mapping of them (``learner``): checked when
    it was made."""
    values = value.values() if isinstance(value, dict) and value else [value]
    return all(isinstance(v, Section) for v in values)


def register(section: str) -> Callable[[type], type]:
    """Class decorator: name a :class:`Section` dataclass's section and store it in Hydra's
    ConfigStore as the structured config ``schema/<group>/<name>`` placed at ``<group>.<name>``
    (``"learner.maml"``: ``schema/learner/maml``), which ``configs/train.yaml`` composes. (Under
    ``schema/``: a group named ``learner`` would make ``armeta-eval learner=<dir>`` a choice of
    it.)"""

    def store(cls: type) -> type:
        cls.section = section
        group, _, name = section.rpartition(".")
        node = OmegaConf.structured(cls)
        OmegaConf.set_readonly(node, False)  # a frozen dataclass's values, overridden as composed
        ConfigStore.instance().store(group=f"schema/{group}", name=name, node=node,
                                     package=section)
        return cls

    return store


def field_type(section: Any, name: str) -> Any:
    """The type the field ``name`` of the dataclass ``section`` is declared with (``Any``:
    ``section`` is no dataclass, a free mapping such as ``benchmark.collector``, or has no such
    field)."""
    if not (isinstance(section, type) and dataclasses.is_dataclass(section)):
        return Any
    return _type_hints(section).get(name, Any)


@functools.cache
def _type_hints(section: type) -> dict[str, Any]:
    return typing.get_type_hints(section)


def declared_type(cfg: DictConfig, key: str) -> Any:
    """The type dotted ``key`` is declared with in the composed ``cfg``: its field's in the
    section that holds it (:func:`field_type`)."""
    parent, _, leaf = key.rpartition(".")
    container = OmegaConf.select(cfg, parent) if parent else cfg
    if not isinstance(container, DictConfig):
        return Any
    return field_type(OmegaConf.get_type(container), leaf)


def _given(declared: Any) -> Any:
    """``declared`` without its ``None`` (``int | None``: ``int``)."""
    if typing.get_origin(declared) in (typing.Union, types.UnionType):
        kinds = [kind for kind in typing.get_args(declared) if kind is not type(None)]
        return kinds[0] if len(kinds) == 1 else declared
    return declared


def reads_as_boolean(declared: Any, value: Any) -> bool:
    """Whether a key declared ``declared`` is a boolean that OmegaConf would take ``value`` for
    only by reading it as one: it reads ``'off'``, ``'yes'``, ``1`` or ``0`` as a boolean
    without a word, so ``learner.maml.first_order=off`` would silently train first-order. The
    one rule for a boolean key, from the command line
    (:func:`armeta_rl.cli.compose.compose_job`, which sees the value before composing converts
    it) and from Python (:class:`Section`): true or false, or null where the key allows it."""
    return _given(declared) is bool and value is not None and not isinstance(value, bool)


def type_words(declared: Any) -> str:
    """What a value of a key declared ``declared`` must be, in words (``an integer``, ``a list
    of numbers``, ...)."""
    kind = _given(declared)
    if kind is list or typing.get_origin(kind) is list:
        element = {int: "integers", float: "numbers", str: "strings", bool: "booleans"}.get(
            next(iter(typing.get_args(kind)), None))
        return f"a list of {element}" if element else "a list"
    return {bool: "a boolean (true or false)", int: "an integer", float: "a number",
            str: "a string"}.get(kind, "a group of keys")


def config_error(error: OmegaConfBaseException) -> ConfigError:
    """OmegaConf's error (a value of the wrong type, a key the schema lacks) as one
    :class:`ConfigError` line naming the key."""
    if isinstance(error, MissingMandatoryValue):
        allowed = "must be set"
    elif getattr(error, "child_node", None) is None:
        allowed = "no such key" if isinstance(error, ConfigKeyError) else (
            str(error).splitlines()[0])
    else:
        allowed = f"must be {type_words(field_type(error.object_type, str(error.key)))}"
    return ConfigError(str(error.full_key), getattr(error, "value", None), allowed)
