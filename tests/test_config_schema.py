"""The config schema: every benchmark × method composes and validates; a table of bad values,
generated from the sections' fields, is refused for every key with a line naming it."""

from __future__ import annotations

import dataclasses
import math
import types
import typing

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from armeta_rl.cli.compose import compose_job, config_dir
from armeta_rl.cli.failures import Refused
from armeta_rl.config import TrainConfig, TrainerConfig, load_run_config, schema, validate
from armeta_rl.config_files import group_choices
from armeta_rl.errors import ConfigError
from armeta_rl.factory import check_method
from armeta_rl.learners.maml import MamlOptions

KINDS = ("sinusoid_uniform", "pendulum_uniform", "point_nav")
"""One benchmark of each kind of collector (regression, system identification, episodes): every
method composes with each; every benchmark composes with MAML and AR-MAML."""


@pytest.fixture(scope="module")
def composed():
    """The ``benchmark/method`` compositions of ``armeta-train``'s config that cover every
    benchmark and every method: each method on each of :data:`KINDS`, each benchmark with MAML
    and AR-MAML (a benchmark selects its collector, a method its learner and risk sections, so
    their pairs meet only through those kinds)."""
    pairs = {(b, m) for b in KINDS for m in group_choices("method")}
    pairs |= {(b, m) for b in group_choices("benchmark") for m in ("maml", "ar_maml")}
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        return {f"{b}/{m}": compose("train", overrides=[f"benchmark={b}", f"method={m}"])
                for b, m in sorted(pairs)}


def test_every_benchmark_and_method_composes_and_validates(composed):
    assert {name.split("/")[0] for name in composed} == set(group_choices("benchmark"))
    assert {name.split("/")[1] for name in composed} == set(group_choices("method"))
    for name, cfg in composed.items():
        config = validate(cfg)
        check_method(config.method)
        assert isinstance(config, TrainConfig), name
        benchmark, method = name.split("/")
        assert (config.benchmark.name, config.method.name) == (benchmark, method)


def sections() -> dict[str, type]:
    """Every section's dataclass by its dotted key: the root's, and each registered learner's
    and risk principle's."""
    found: dict[str, type] = {}

    def walk(cls: type, prefix: str) -> None:
        found[prefix] = cls
        hints = typing.get_type_hints(cls)
        for spec in dataclasses.fields(cls):
            if dataclasses.is_dataclass(hints[spec.name]):
                walk(hints[spec.name], f"{prefix}{spec.name}.")

    walk(TrainConfig, "")
    typed = schema()
    for group in ("learner", "risk"):
        for name in typed[group]:
            walk(OmegaConf.get_type(typed[group][name]), f"{group}.{name}.")
    return found


CANDIDATES = [0, -1, 0.0, -0.5, 1.0, 1.5, 2**64, -(2**63) - 1, "bogus", [], [0], [-1], [1.5],
              [0.5, 1.2], ["x"], float("nan"), float("inf")]
"""Values of many types: the out-of-range ones for a key are those of its type it refuses."""


def conforms(value: object, hint: object) -> bool:
    """Whether ``value`` has the type ``hint`` (``X | None``, ``list[X]``, a scalar)."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return conforms(value, args[0])
    if typing.get_origin(hint) is list:
        return isinstance(value, list) and all(conforms(v, args[0]) for v in value)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, hint) and not (hint is int and isinstance(value, bool))


def bad_values() -> list[tuple[str, object]]:
    """``(key, value)`` for every ranged field of every section: each candidate of its type that
    its range (or finiteness) refuses."""
    cases = []
    for prefix, cls in sections().items():
        hints = typing.get_type_hints(cls)
        for spec in dataclasses.fields(cls):
            test = spec.metadata.get("test")
            hint = hints[spec.name]
            scalar_float = typing.get_origin(hint) is not list and float in (
                hint, *typing.get_args(hint))
            if test is None and not scalar_float:
                continue
            refused = [v for v in CANDIDATES if conforms(v, hint) and (
                (scalar_float and not math.isfinite(v)) or (test is not None and not test(v)))]
            assert refused, f"no candidate value is out of {prefix}{spec.name}'s range"
            cases.extend((f"{prefix}{spec.name}", v) for v in refused)
    return cases


def test_every_ranged_key_refuses_its_bad_values_with_a_line_naming_it(composed):
    cases = bad_values()
    assert len({key for key, _ in cases}) >= 50
    base = composed["sinusoid_uniform/ar_maml"]
    for key, value in cases:
        cfg = base.copy()
        OmegaConf.update(cfg, key, value)
        with pytest.raises(ConfigError) as error:
            validate(cfg)
        assert error.value.key == key, (key, value, str(error.value))
        assert str(error.value).startswith(f"config key '{key}' = ")
        assert "\n" not in str(error.value)


@pytest.mark.parametrize(("override", "words"), [
    ("trainer.iterations=abc", "must be an integer"),
    ("trainer.iterations=1.5", "must be an integer"),
    ("learner.maml.inner_lr=true", "must be a number"),
    ("learner.maml.first_order=off", "must be a boolean (true or false)"),
    ("learner.maml.first_order=1", "must be a boolean (true or false)"),
    ("learner.maml.hidden=[1.5]", "must be a list of integers"),
    ("trainer.iteratons=5", "did you mean 'trainer.iterations'?"),
])
def test_a_value_of_the_wrong_type_or_an_unknown_key_is_one_line_naming_the_key(override, words):
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None), \
            pytest.raises(Refused) as error:
        compose_job([override])
    key = override.split("=")[0]
    assert str(error.value).startswith(f"config key '{key}' = "), str(error.value)
    assert words in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize(("options", "key", "words"), [
    ({"first_order": "off"}, "learner.maml.first_order", "must be a boolean (true or false)"),
    ({"first_order": 1}, "learner.maml.first_order", "must be a boolean (true or false)"),
    ({"inner_lr": "0.5"}, "learner.maml.inner_lr", "must be a number"),
    ({"inner_lr": None}, "learner.maml.inner_lr", "must be a number"),
    ({"hidden": [1.5]}, "learner.maml.hidden", "must be a list of integers"),
    ({"hidden": ["4"]}, "learner.maml.hidden", "must be a list of integers"),
    ({"iterations": "5"}, "trainer.iterations", "must be an integer"),
    ({"progress": "yes"}, "trainer.progress", "must be a boolean (true or false)"),
])
def test_a_section_made_in_python_refuses_what_composing_would_refuse_or_convert(
        options, key, words):
    """The command line's type rules, from Python: a value OmegaConf takes only by converting
    it (which the dataclass would keep unconverted) is refused as a wrong type."""
    section = TrainerConfig if key.startswith("trainer.") else MamlOptions
    with pytest.raises(ConfigError) as error:
        section(**options)
    value = next(iter(options.values()))
    assert str(error.value) == f"config key '{key}' = {value!r}: {words}"


@pytest.mark.parametrize(("good", "bad"), [(0.5, "0.5"), (1.0, True), (1.0, "1")])
def test_a_section_typed_once_refuses_a_value_that_reads_the_same(good, bad):
    """A section's typed values are made once per type and values (:meth:`Section.typed`): a
    value that reads or compares the same as one typed before (``'0.5'`` after ``0.5``) is
    still refused, and what ``typed`` hands out cannot be changed."""
    typed = MamlOptions(inner_lr=good).typed()
    assert MamlOptions(inner_lr=good).typed() is typed
    with pytest.raises(ConfigError, match="must be a number"):
        MamlOptions(inner_lr=bad)
    with pytest.raises(OmegaConfBaseException):
        typed.inner_lr = 2.0


def test_a_saved_config_with_a_key_this_version_lacks_is_refused_in_one_line(tmp_path, composed):
    cfg = OmegaConf.create(OmegaConf.to_container(composed["pendulum_uniform/maml"],
                                                  resolve=True))
    OmegaConf.save(cfg, tmp_path / "config.yaml")
    assert OmegaConf.to_container(load_run_config(tmp_path, "learner")) == (
        OmegaConf.to_container(cfg))
    OmegaConf.update(cfg, "trainer.compile", False, force_add=True)
    OmegaConf.save(cfg, tmp_path / "config.yaml")
    with pytest.raises(ConfigError, match="'learner' = .*does not fit this version: .*"
                                          "'trainer.compile'"):
        load_run_config(tmp_path, "learner")


def test_a_saved_config_read_twice_is_a_fresh_equal_reading(tmp_path, composed):
    """A run's config is merged into the schema once per text and registered sections: every
    reading equals a fresh merge, is a copy of its own (a change to one does not reach the
    next), a refusal names each caller's key and place, and a section registered since is in
    the next reading."""
    from hydra.core.config_store import ConfigStore

    from armeta_rl.config import read_run_config

    text = OmegaConf.to_yaml(composed["pendulum_uniform/maml"], resolve=True)
    first = read_run_config(text, "resume", "a")
    fresh = OmegaConf.merge(schema(), OmegaConf.create(text))
    assert first == fresh
    first.trainer.meta_batch = -1
    assert read_run_config(text, "resume", "a") == fresh
    broken = text.replace("trainer:", "trainer: [", 1)
    for key, where in (("resume", "a"), ("learner", "b")):
        with pytest.raises(ConfigError, match=f"'{key}' = '{where}': its config.yaml cannot "
                                              "be read"):
            read_run_config(broken, key, where)
    store = ConfigStore.instance()
    node = store.load("schema/learner/maml.yaml").node
    store.store(group="schema/learner", name="maml_copy", node=node)
    try:
        assert "maml_copy" in read_run_config(text, "resume", "a").learner
    finally:
        del store.repo["schema"]["learner"]["maml_copy.yaml"]
    assert "maml_copy" not in read_run_config(text, "resume", "a").learner
