"""The config schema: every benchmark × method composes to its pinned values and passes; a
table of bad values, generated from the schema, is refused for every key with a line naming it.

``tests/data/compositions.json`` pins a digest of every composition. After changing a value in
``configs/`` on purpose, regenerate it with ``python tests/test_config_schema.py``.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import sys
import typing
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from armeta_rl.cli import config_dir, group_choices
from armeta_rl.config import TrainSchema, _conforms, _optional, check_config, schema_keys
from armeta_rl.errors import ConfigError

PINNED = Path(__file__).parent / "data" / "compositions.json"


def digest(cfg) -> str:
    """A digest of a composed config's values (integers as floats: a schema may not change a
    value, but may say that a number written ``1`` is the float ``1.0``)."""

    def canonical(value):
        if isinstance(value, dict):
            return {k: canonical(v) for k, v in value.items()}
        if isinstance(value, list):
            return [canonical(v) for v in value]
        if isinstance(value, int) and not isinstance(value, bool):
            return float(value)
        return value

    values = canonical(OmegaConf.to_container(cfg, resolve=True))
    return hashlib.sha256(json.dumps(values, sort_keys=True).encode()).hexdigest()[:16]


def compositions() -> dict[str, object]:
    """Every ``benchmark/method`` composition of ``armeta-train``'s config."""
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        return {
            f"{b}/{m}": compose("train", overrides=[f"benchmark={b}", f"method={m}"])
            for b in group_choices("benchmark")
            for m in group_choices("method")
        }


@pytest.fixture(scope="module")
def composed():
    return compositions()


def test_every_benchmark_and_method_composes_to_its_pinned_values_and_passes(composed):
    pinned = json.loads(PINNED.read_text())
    assert sorted(composed) == sorted(pinned)
    for name, cfg in composed.items():
        assert digest(cfg) == pinned[name], name
        check_config(cfg)


BAD_TYPE = {bool: ["off", "maybe", 1], int: ["abc", 1.5, True], float: ["abc", True, "nan"],
            str: [3, True], list: ["abc", 5], dict: ["abc"]}
CANDIDATES = [0, -1, 0.0, -0.5, 1.0, 1.5, 2**64, -(2**63) - 1, "bogus", [], [0], [-1], [1.5],
              [0.5, 1.2], ["x"]]
"""Values of many types: the out-of-range ones for a key are those of its type it refuses."""


def field_hint(key: str) -> object:
    """The annotation of the schema field of dotted ``key``."""
    schema, *path, leaf = [TrainSchema, *key.split(".")]
    for name in path:
        hint = typing.get_type_hints(schema)[name]
        schema = _optional(hint) or hint
    return typing.get_type_hints(schema)[leaf]


def bad_values(composed) -> list[tuple[str, object, str]]:
    """``(key, bad value, name of a composition that has the key)`` for every schema leaf: wrong
    types, and every candidate of the right type that the key's range refuses."""
    cases = []
    for key, spec in schema_keys().items():
        hint = field_hint(key)
        kind = _optional(hint) or hint
        kind = typing.get_origin(kind) or kind
        if dataclasses.is_dataclass(kind) or kind is typing.Any:
            continue
        parent = key.rsplit(".", 1)[0] if "." in key else None
        owners = [n for n, cfg in composed.items()
                  if parent is None or OmegaConf.select(cfg, parent) is not None]
        owner = next((n for n in owners if OmegaConf.select(composed[n], key) is not None),
                     owners[0])
        cases.extend((key, value, owner) for value in BAD_TYPE[kind])
        test = spec.metadata["test"]
        if test is not None:
            refused = [v for v in CANDIDATES if _conforms(v, hint) and not test(v)]
            assert refused, f"no candidate value is out of {key}'s range"
            cases.extend((key, value, owner) for value in refused)
    return cases


def test_every_key_refuses_its_bad_values_with_a_line_naming_it(composed):
    cases = bad_values(composed)
    assert len({key for key, _, _ in cases}) >= 60
    for key, value, owner in cases:
        cfg = composed[owner].copy()
        OmegaConf.update(cfg, key, value, force_add=True)
        with pytest.raises(ConfigError) as error:
            check_config(cfg)
        assert error.value.key == key, (key, value, str(error.value))
        assert str(error.value).startswith(f"config key '{key}' = ")
        assert "\n" not in str(error.value)


if __name__ == "__main__":
    PINNED.write_text(json.dumps({n: digest(c) for n, c in compositions().items()}, indent=1,
                                 sort_keys=True) + "\n")
    sys.exit(0)


@pytest.mark.parametrize("key", ["benchmark.collector.compile", "benchmark.eval_collector.compile"])
def test_a_saved_run_loads_without_a_removed_key_at_todays_behaviour_and_refuses_another(
    tmp_path, key
):
    """A config saved before the compiled sys-id step was removed holds ``compile: false``: it
    loads, without the key; ``compile: true`` asked for what no longer exists: one line."""
    from armeta_rl.config import load_run_config

    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        composed = compose("train", overrides=["benchmark=pendulum_uniform"])
    cfg = OmegaConf.create(OmegaConf.to_container(composed, resolve=True))  # as a run saves it
    for value in (False, True):
        saved = copy.deepcopy(cfg)
        OmegaConf.update(saved, key, value, force_add=True)
        OmegaConf.save(saved, tmp_path / "config.yaml")
        if value:
            with pytest.raises(ConfigError, match=f"'{key}' = True: was removed"):
                load_run_config(tmp_path, "learner")
        else:
            loaded = load_run_config(tmp_path, "learner")
            assert OmegaConf.select(loaded, key, default="absent") == "absent"
            assert OmegaConf.to_container(loaded) == OmegaConf.to_container(cfg)
