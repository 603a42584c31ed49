"""``--help`` of ``armeta-train`` and ``armeta-eval``: the usage, the groups a command line
chooses from and, for ``armeta-train``, every key with its type, default, range and one-line doc,
read from the config's dataclasses themselves (:mod:`armeta_rl.config`; a learner's or a risk
principle's section from its module, ``--help learner.maml``)."""

from __future__ import annotations

import dataclasses
import inspect
import io
import re
import tokenize
from collections.abc import Sequence
from typing import Any

from armeta_rl.config_files import group_choices

SECTIONS = ("learner", "risk")
"""The config's mappings of registered sections (``learner.maml``, ``risk.ar``), whose modules
import torch: listed when a ``--help`` word names them."""


def print_help(prog: str, config_name: str, groups: tuple[str, ...], usage: str,
               sections: Sequence[str] = ()) -> None:
    """``--help``: the usage, the groups a command line chooses from, the keys of
    ``armeta-train`` (those under ``sections``, the words given after ``--help``, when there are
    some) and where to see the composed config. The root keys come from :mod:`armeta_rl.config`
    alone, and a learner's or a risk principle's only when a word names it: composing the config
    would import every learner (torch, TorchRL, MuJoCo) for a page of text."""
    lines = [f"{prog}: {usage}", "", "Configuration groups (group=option):"]
    lines += [f"  {group}: {', '.join(group_choices(group))}" for group in groups] or ["  none"]
    if config_name == "train":
        lines += ["", "Keys (key=value: type, default, range; a benchmark sets its own "
                  "defaults):", *key_lines(sections)]
    lines += ["", f"Config: configs/{config_name}.yaml and the dataclasses it lists; override any "
              "key with key=value, add one with +key=value (docs/configuration.md).",
              f"The composed config of a command line, every key with its value: {prog} "
              "[overrides] --cfg job",
              "Hydra's own flags (-m, --cfg job, -sc install=bash, ...): --hydra-help"]
    print("\n".join(lines))


def key_lines(sections: Sequence[str]) -> list[str]:
    """A line for every key under one of ``sections`` (all of the root's when there are none,
    with a pointer to the learners' and risk principles' sections)."""
    from armeta_rl.config import TrainConfig

    wanted = [s for s in sections if s.split(".")[0] in SECTIONS]
    lines = [line for name, line in section_keys(TrainConfig, "") if name not in SECTIONS
             and (not sections or any(_under(name, s) for s in sections))]
    if not sections:
        lines.append(f"  {'.<name>.*, '.join(SECTIONS)}.<name>.*: a learner's and a risk "
                     f"principle's options: --help {' or '.join(SECTIONS)} (or learner.maml, "
                     "risk.ar, ...)")
    if wanted:
        from hydra.core.config_store import ConfigStore
        from omegaconf import OmegaConf

        import armeta_rl.factory  # noqa: F401  registers every learner's and principle's section

        store = ConfigStore.instance()
        for group in SECTIONS:
            for entry in store.list(f"schema/{group}"):
                section = OmegaConf.get_type(store.load(f"schema/{group}/{entry}").node)
                prefix = f"{group}.{entry.removesuffix('.yaml')}"
                lines += [line for name, line in section_keys(section, prefix)
                          if any(_under(name, s) for s in wanted)]
    if sections and not lines:
        lines.append(f"  no key under {', '.join(sections)}")
    return lines


def _under(name: str, section: str) -> bool:
    return name == section or name.startswith(f"{section}.")


def section_keys(section: type, prefix: str) -> list[tuple[str, str]]:
    """Every key of the :class:`~armeta_rl.fields.Section` dataclass ``section`` placed at
    ``prefix`` (nested sections' keys included) and its line: type, default, range and the
    comment written with its field."""
    from armeta_rl.fields import field_type, type_words

    docs = field_docs(section)
    keys = []
    for spec in dataclasses.fields(section):
        name = f"{prefix}.{spec.name}" if prefix else spec.name
        declared = field_type(section, spec.name)
        if dataclasses.is_dataclass(declared):
            keys += section_keys(declared, name)
            continue
        default = (spec.default_factory() if spec.default_factory is not dataclasses.MISSING
                   else spec.default)
        allowed = spec.metadata.get("allowed")
        line = f"  {name} = {_shown(default)}: {type_words(declared)}"
        line += f", {allowed}" if allowed else ""
        keys.append((name, line + (f". {docs[spec.name]}" if spec.name in docs else "")))
    return keys


def _shown(value: Any) -> str:
    """``value`` as a command line writes it."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list):
        return f"[{','.join(_shown(v) for v in value)}]"
    return "''" if value == "" else str(value)


def field_docs(section: type) -> dict[str, str]:
    """The comment written with each field of the dataclass ``section`` (the comment lines just
    above it and the one after it on its line), as one line: a key's doc is where its field is
    declared."""
    source = inspect.getsource(section)
    comments = {token.start[0]: token.string.lstrip("#").strip()
                for token in tokenize.generate_tokens(io.StringIO(source).readline)
                if token.type == tokenize.COMMENT}
    lines = source.splitlines()
    body = next(number for number, line in enumerate(lines) if line.startswith("class ")) + 1
    indent = re.match(r"\s*", lines[body]).group()
    names = {spec.name for spec in dataclasses.fields(section)}
    docs = {}
    for number, line in enumerate(lines, start=1):
        field = re.match(rf"{indent}(\w+)\s*:", line)
        if field is None or field.group(1) not in names:
            continue
        above = number - 1
        while above in comments and lines[above - 1].strip().startswith("#"):
            above -= 1
        words = [comments[n] for n in range(above + 1, number)]
        words += [comments[number]] if number in comments else []
        if words:
            docs[field.group(1)] = " ".join(words)
    return docs
