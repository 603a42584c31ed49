"""Composing and checking ``armeta-train``'s and ``armeta-eval``'s configs from command-line
words: each job's overrides (one list per combination of a ``-m`` sweep), the config Hydra
composes from them, refused as one line naming the key, the value and what is allowed (the likely
key, for a misspelt one), and the config validated into a :class:`~armeta_rl.config.TrainConfig`.
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from armeta_rl.cli.failures import Refused
from armeta_rl.config_files import config_files, group_choices
from armeta_rl.errors import ConfigError

if TYPE_CHECKING:
    from armeta_rl.config import TrainConfig


GROUPS = ("benchmark", "method", "logger")
"""The config groups a command line chooses from (``benchmark=point_nav``)."""


_ABSENT = object()


def config_dir() -> Path:
    """The Hydra config directory, ready to compose from: importing :mod:`armeta_rl.factory`
    registers every learner's and risk principle's options and :mod:`armeta_rl.config`'s root
    schema in Hydra's ConfigStore. That import loads the learners (torch), so it is made here,
    where configs are composed, and not by ``import armeta_rl`` or by importing this module."""
    import armeta_rl.factory  # noqa: F401

    return config_files()


def _has_key(cfg: DictConfig, key: str) -> bool:
    """Whether dotted ``key`` is in ``cfg`` (also when its value is the mandatory ``???``)."""
    from omegaconf.errors import MissingMandatoryValue

    try:
        return OmegaConf.select(cfg, key, default=_ABSENT, throw_on_missing=True) is not _ABSENT
    except MissingMandatoryValue:
        return True


def _deepest_existing(cfg: DictConfig, key: str) -> tuple[str, object]:
    """The longest prefix of dotted ``key`` that ``cfg`` has, and its node (the root: ``""``)."""
    parts = key.split(".")
    for end in range(len(parts) - 1, 0, -1):
        prefix = ".".join(parts[:end])
        if _has_key(cfg, prefix):
            return prefix, OmegaConf.select(cfg, prefix)
    return "", cfg


def _unknown_key_message(cfg: DictConfig, key: str, value: str, choices: list[str]) -> str:
    """One line for an override of a key ``cfg`` (composed with the group ``choices``) lacks:
    what exists there, the likely typo, and how to add a new key on purpose."""
    parent, node = _deepest_existing(cfg, key)
    where = f"'{parent}'" if parent else "the top level"
    message = f"config key '{key}' = {value}: no such key"
    if choices:
        message += f" with {' '.join(choices)}"
    if not isinstance(node, DictConfig):
        return f"{message} ({where} is a value, not a group of keys)"
    names = sorted(str(name) for name in node)
    if names:
        message += f"; {where} has: {', '.join(names)}"
        missing = key[len(parent) + 1 :] if parent else key
        close = difflib.get_close_matches(missing.split(".")[0], names, n=1)
        if close:
            message += f" (did you mean '{parent + '.' if parent else ''}{close[0]}'?)"
    else:
        message += f"; {where} has no keys yet"
    return message + f"; to add a new key write +{key}={value}"


def parse_override(arg: str) -> Any:
    """The Hydra override ``arg`` parses to (:class:`Refused` if it cannot be read)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        (override,) = OverridesParser.create().parse_overrides([arg])
    except HydraException as error:
        raise Refused(f"cannot read the override {arg!r}: {str(error).splitlines()[0]}") from None
    return override


def is_hydra_key(key: str) -> bool:
    return key.split(".")[0].split("/")[0] == "hydra"


def job_overrides(args: Sequence[str], groups: tuple[str, ...] = GROUPS) -> list[list[str]]:
    """The config overrides (not ``hydra.*``) of every job the command line starts: one list for
    each combination of the values of ``-m`` sweeps such as ``trainer.iterations=5,0``. An
    unknown choice of a group in ``groups`` (``benchmark=``, also inside a sweep) is refused."""
    import itertools

    per_arg = []
    for arg in args:
        if arg.startswith("-") or "=" not in arg:
            continue
        override = parse_override(arg)
        key = override.key_or_group
        if is_hydra_key(key):
            continue
        values = ([str(v) for v in override.sweep_string_iterator()]
                  if override.is_sweep_override() else [arg.split("=", 1)[1]])
        if key in groups:
            allowed = group_choices(key)
            for choice in values:
                if choice not in allowed:
                    raise Refused(f"config key '{key}' = {choice!r}: allowed: "
                                   f"{', '.join(allowed)}")
        name = arg.split("=", 1)[0]
        per_arg.append([f"{name}={value}" for value in values] if len(values) > 1 else [arg])
    return [list(job) for job in itertools.product(*per_arg)]


def compose_job(job: list[str], config_name: str = "train") -> DictConfig:
    """Compose ``config_name`` with the overrides ``job`` (inside Hydra's initialized config
    dir). A key the config lacks or a value of the wrong type is refused as one line
    (:class:`Refused`). Composing reads ``off`` or ``1`` as a boolean without a word, so a
    boolean key's override is checked here, where its value is still the one given
    (:func:`armeta_rl.fields.reads_as_boolean`)."""
    from hydra import compose
    from hydra.errors import ConfigCompositionException, HydraException

    try:
        cfg = compose(config_name, overrides=job)
    except ConfigCompositionException as error:
        raise Refused(_composition_message(job, config_name, error)) from None
    except HydraException as error:
        raise Refused(" ".join(str(error).split())) from None
    _check_booleans(cfg, job)
    return cfg


def _check_booleans(cfg: DictConfig, job: list[str]) -> None:
    """Refuse an override of ``job`` that ``cfg`` took for a boolean only by reading it as one
    (:func:`armeta_rl.fields.reads_as_boolean`)."""
    from armeta_rl.fields import declared_type, reads_as_boolean, type_words

    for arg in job:
        override = parse_override(arg)
        key, value = override.key_or_group, override.value()
        declared = declared_type(cfg, key)
        if reads_as_boolean(declared, value):
            raise Refused(str(ConfigError(key, value, f"must be {type_words(declared)}")))


def compose_run(job: list[str], hydra_words: list[str]) -> tuple[DictConfig, Path]:
    """A single run's config composed once, with its Hydra config (inside Hydra's initialized
    config dir): the job's config, and the directory Hydra will run it in (``hydra.run.dir``
    resolved now, its ``${now:...}`` included, so the CLI can check and lock it before Hydra
    writes there). A bad word is refused as :func:`compose_job` refuses the job's overrides
    ``job`` and :func:`check_hydra` the ``hydra.*`` words ``hydra_words``."""
    from hydra import compose
    from hydra.errors import HydraException
    from omegaconf import open_dict, read_write
    from omegaconf.errors import OmegaConfBaseException

    try:
        cfg = compose("train", overrides=[*job, *hydra_words], return_hydra_config=True)
    except (HydraException, OmegaConfBaseException) as error:
        compose_job(job)  # the job's own words refused first, as they are alone
        raise Refused(_hydra_message(hydra_words, _causes(error))) from None
    _check_booleans(cfg, job)
    run_dir = Path(OmegaConf.select(cfg, "hydra.run.dir"))
    with read_write(cfg), open_dict(cfg):
        del cfg["hydra"]
    return cfg, run_dir


def _composition_message(job: list[str], config_name: str, error: Exception) -> str:
    """One line for the override of ``job`` that Hydra could not compose: a missing key (with
    what is there and the likely one) or a value of the wrong type."""
    from hydra import compose

    text = str(error)
    for arg in job:
        key, value = arg.lstrip("+~").split("=", 1) if "=" in arg else (arg, "")
        if f"'{key}'" not in text and f"override {arg}" not in text:
            continue
        others = [a for a in job if a != arg]
        try:
            cfg = compose(config_name, overrides=others)
        except Exception:  # another override fails too: reported on its own
            break
        choices = [a for a in others if a.split("=")[0] in GROUPS]
        if not _has_key(cfg, key):
            return _unknown_key_message(cfg, key, value, choices)
        from armeta_rl.fields import declared_type, type_words

        return f"config key '{key}' = {value}: must be {type_words(declared_type(cfg, key))}"
    return " ".join(text.split())


def check_hydra(args: Sequence[str], config_name: str) -> None:
    """Compose ``config_name`` with the ``hydra.*`` and ``hydra/<group>=`` words of ``args`` and
    its Hydra config, as Hydra will before its first job: a word Hydra would refuse (a value of
    the wrong type, a key its launcher lacks, a choice it does not have) is refused here as one
    line naming its key and value, where Hydra's own message spans several."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    words = hydra_words(args)
    if not words:
        return
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        try:
            compose(config_name, overrides=words, return_hydra_config=True)
        except (HydraException, OmegaConfBaseException) as error:
            raise Refused(_hydra_message(words, _causes(error))) from None


def hydra_words(args: Sequence[str]) -> list[str]:
    """The ``hydra.*`` and ``hydra/<group>=`` overrides of the command line ``args``."""
    return [a for a in args if "=" in a and not a.startswith("-")
            and is_hydra_key(a.split("=", 1)[0].lstrip("+~"))]


def _causes(error: BaseException) -> str:
    """``error`` and the chain of its causes, a line each: Hydra prints the chain, and the
    reason is in it."""
    texts, cause = [], error
    while cause is not None:
        texts.append(str(cause))
        cause = cause.__cause__
    return "\n".join(texts)


def _hydra_message(words: Sequence[str], text: str) -> str:
    """One line for Hydra's refusal ``text`` of one of ``words``: its key and value, and what
    Hydra says is wrong or allows."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    options = []
    if any(line.startswith("Available options") for line in lines):
        start = next(i for i, line in enumerate(lines) if line.startswith("Available options"))
        options = [line for line in lines[start + 1:] if not line.startswith(
            ("Config search path", "provider="))]
        options = options[:next((i for i, o in enumerate(options) if " " in o), len(options))]
    reason = next((line for line in lines if not line.startswith((
        "Error merging override", "Could not override", "To append", "full_key:",
        "object_type=", "In '", "Available options", "Config search path", "provider="))),
        lines[0] if lines else "refused by Hydra")
    named = [word for word in words if f"override {word}" in text
             or f"{word.lstrip('+~').replace('=', '/', 1)}'" in text]
    for word in named or [word for word in reversed(words)
                          if word.lstrip("+~").split("=", 1)[0] in text]:
        key, value = word.lstrip("+~").split("=", 1)
        allowed = f"allowed: {', '.join(options)}" if options else reason
        return f"config key '{key}' = {value!r}: {allowed}"
    return " ".join(text.split())


def checked(cfg: DictConfig) -> TrainConfig:
    """The composed ``cfg`` validated (:func:`armeta_rl.config.validate`) with its method's
    names checked against the registries (:func:`armeta_rl.factory.check_method`)."""
    from armeta_rl.config import validate
    from armeta_rl.factory import check_method

    config = validate(cfg)
    check_method(config.method)
    return config


def check_jobs(args: Sequence[str]) -> dict[tuple[tuple[str, str], ...], TrainConfig]:
    """Compose and validate the ``armeta-train`` config of every job on the command line (each
    combination of a ``-m`` sweep), so that no job trains before every job's values are known to
    be good; returns their :class:`~armeta_rl.config.TrainConfig` by the job's overrides
    (:func:`job_key`).
    :class:`Refused` for the first bad one."""
    from hydra import initialize_config_dir


    jobs = job_overrides(args)
    configs = {}
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        for job in jobs:
            where = f" (job {' '.join(job)})" if len(jobs) > 1 else ""
            try:
                config = checked(compose_job(job))
            except Refused as refused:
                raise Refused(f"{refused}{where}") from None
            except ConfigError as error:
                raise Refused(f"{error}{where}") from None
            configs[job_key(job)] = config
    return configs


def job_key(overrides: Sequence[str]) -> tuple[tuple[str, str], ...]:
    """The overrides of a job as the values they set, by key: the same for the words a command
    line gave and the words Hydra hands the job (which writes ``false`` as ``False``)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return tuple((o.get_key_element(), str(o.value()))
                 for o in OverridesParser.create().parse_overrides(list(overrides)))
