"""A results directory's runs in two compact files beside its reports, from which every report
is rebuilt without the run directories (``armeta-reproduce … pack=true``, docs/reproducing.md).

- ``reports.jsonl.gz``: one JSON line per section of every evaluation report (``eval.json``,
  ``eval_vs_<name>.json``, ``eval_shifts.json``) of every run: the run (``run``:
  ``runs/<benchmark>/<name>/seed<k>``), the report file (``file``), the section (``section``:
  ``initial``, ``adversarial``, ``shift/<name>``, …) and its place among the report's keys
  (``position``), the report's other fields (``report``: metric, benchmark, method, seed,
  config digest, learner and adversary paths) and the section's own fields (mean, sem, cvar,
  cvar_sem, n_tasks, …, per_task).
- ``configs.jsonl.gz``: the first line holds the base config (``base``: each key's most common
  value over the runs, nested as in a ``config.yaml``); then one line per run: ``run``, the
  dotted keys whose value differs from the base or that the base lacks (``set``), the base's keys
  the run lacks (``unset``), and where the run's keys come in another order than the base's, that
  order (``order``). A config that cannot be written so is kept as its text (``text``).

Both are plain gzipped JSON lines (``pandas.read_json(path, lines=True)``); floats are written
as Python writes them, so every value reads back bit for bit: unpacking gives each report and
config.yaml byte for byte (:func:`unpack`).
"""

from __future__ import annotations

import gzip
import json
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from armeta_rl.config import CONFIG_FILE
from armeta_rl.run_files import FileRefused, gunzip, read_file
from armeta_rl.trainers.run_dir import write_atomically, write_text_atomically

REPORTS_FILE = "reports.jsonl.gz"
CONFIGS_FILE = "configs.jsonl.gz"
LINE_KEYS = ("run", "file", "section", "position", "report")
"""A report line's own keys; a section's fields come after them."""
PACKED_BYTES = 2**28
"""The most a compact file is read, compressed and decompressed (256 MiB; the largest
committed, table1 with its shift suite at the paper profile, holds 5 MiB)."""
LINE_BYTES = 2**24
"""The most a line of a compact file may hold (16 MiB; a section of a report holds a few KiB)."""

RunFile = tuple[str, str]
"""A report's place: (its run's directory relative to the results directory, its file name)."""


@dataclass(frozen=True)
class Packed:
    """The packed runs of a results directory: every report by (run, file name) and every
    run's ``config.yaml`` text by run."""

    reports: Mapping[RunFile, dict[str, Any]] = field(default_factory=dict)
    configs: Mapping[str, str] = field(default_factory=dict)


NOTHING_PACKED = Packed()


def report_lines(reports: Mapping[RunFile, dict[str, Any]]) -> list[dict[str, Any]]:
    """The lines of ``reports.jsonl.gz``: one per section (a top-level object) of every report,
    in run and file order; a report without sections gets one line with ``section`` null."""
    lines = []
    for (run, file), report in sorted(reports.items()):
        fields = {key: value for key, value in report.items() if not isinstance(value, dict)}
        sections = [(i, key, value) for i, (key, value) in enumerate(report.items())
                    if isinstance(value, dict)]
        for position, name, section in sections or [(None, None, {})]:
            clash = set(section) & set(LINE_KEYS)
            if clash:
                raise ValueError(f"{run}/{file}: section {name!r} has a field named "
                                 f"{sorted(clash)[0]!r}, which a packed line uses")
            lines.append({"run": run, "file": file, "section": name, "position": position,
                          "report": fields, **section})
    return lines


def reports_of(lines: Iterable[dict[str, Any]]) -> dict[RunFile, dict[str, Any]]:
    """The reports that :func:`report_lines` packed, with their keys in their order."""
    parts: dict[RunFile, tuple[dict[str, Any], dict[int, tuple[str, dict[str, Any]]]]] = {}
    for line in lines:
        fields, sections = parts.setdefault((line["run"], line["file"]), (line["report"], {}))
        if line["section"] is not None:
            sections[line["position"]] = (line["section"], {
                key: value for key, value in line.items() if key not in LINE_KEYS})
    reports = {}
    for place, (fields, sections) in parts.items():
        others = iter(fields.items())
        reports[place] = dict(sections[i] if i in sections else next(others)
                              for i in range(len(fields) + len(sections)))
    return reports


def _leaves(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """The config's values by dotted key, in order (an empty mapping is a value)."""
    leaves = {}
    for key, value in tree.items():
        if not isinstance(key, str) or "." in key or not key:
            raise ValueError(f"key {key!r} cannot be part of a dotted key")
        if isinstance(value, dict) and value:
            leaves.update(_leaves(value, f"{prefix}{key}."))
        else:
            leaves[f"{prefix}{key}"] = value
    return leaves


def _tree(leaves: Mapping[str, Any]) -> dict[str, Any]:
    tree: dict[str, Any] = {}
    for dotted, value in leaves.items():
        *parents, last = dotted.split(".")
        node = tree
        for key in parents:
            node = node.setdefault(key, {})
        node[last] = value
    return tree


def _same(a: Any, b: Any) -> bool:
    """Equal and of the same types (``1``, ``1.0`` and ``true`` are three values)."""
    return json.dumps(a) == json.dumps(b)


def _yaml(tree: Mapping[str, Any]) -> str:
    return OmegaConf.to_yaml(OmegaConf.create(dict(tree)))


def _parsed(text: str) -> dict[str, Any]:
    return OmegaConf.to_container(OmegaConf.create(text), resolve=False)


def config_lines(configs: Mapping[str, str]) -> list[dict[str, Any]]:
    """The lines of ``configs.jsonl.gz`` for the ``config.yaml`` texts ``configs`` (by run): the
    base, then each run's differences from it (its text where they do not give it back)."""
    leaves: dict[str, dict[str, Any]] = {}
    texts: dict[str, str] = {}
    for run, text in sorted(configs.items()):
        try:
            flat = _leaves(_parsed(text))
            if _yaml(_tree(flat)) != text:
                raise ValueError("the config's YAML is not what its values give")
        except ValueError:
            texts[run] = text
            continue
        leaves[run] = flat
    counts: dict[str, Counter] = {}
    for flat in leaves.values():
        for key, value in flat.items():
            counts.setdefault(key, Counter())[json.dumps(value)] += 1
    base = {key: json.loads(count.most_common(1)[0][0]) for key, count in counts.items()
            if count.total() * 2 >= len(leaves)}
    lines: list[dict[str, Any]] = [{"run": None, "base": _tree(base)}]
    for run in sorted(configs):
        if run in texts:
            lines.append({"run": run, "text": texts[run]})
            continue
        flat = leaves[run]
        line = {"run": run,
                "set": {k: v for k, v in flat.items() if k not in base or not _same(v, base[k])},
                "unset": [k for k in base if k not in flat]}
        if _yaml(_tree(_run_leaves(base, line))) != configs[run]:
            line["order"] = list(flat)
        lines.append(line)
    return lines


def _run_leaves(base: Mapping[str, Any], line: Mapping[str, Any]) -> dict[str, Any]:
    unset = set(line["unset"])
    flat = {key: value for key, value in base.items() if key not in unset}
    flat.update(line["set"])
    if "order" in line:
        flat = {key: flat[key] for key in line["order"]}
    return flat


def configs_of(lines: Iterable[dict[str, Any]]) -> dict[str, str]:
    """The ``config.yaml`` texts that :func:`config_lines` packed, by run."""
    lines = iter(lines)
    base = _leaves(next(lines)["base"])
    return {line["run"]: line["text"] if "text" in line else _yaml(_tree(_run_leaves(base, line)))
            for line in lines}


def _write_lines(path: Path, lines: Iterable[dict[str, Any]]) -> None:
    text = "".join(json.dumps(line, separators=(",", ":")) + "\n" for line in lines)
    data = gzip.compress(text.encode(), mtime=0)
    write_atomically(path, lambda staged: staged.write_bytes(data))


def _read_lines(path: Path, results: Path) -> list[dict[str, Any]]:
    """The JSON lines of the compact file ``path`` of ``results`` (none when it is absent), read
    bounded (:data:`PACKED_BYTES` compressed and decompressed, :data:`LINE_BYTES` a line).

    Raises:
        FileRefused: ``path`` is not a regular file of one link, is larger, cut short, damaged,
            or holds a line that is too long or not a JSON object.
    """
    try:
        data = gunzip(read_file(path, PACKED_BYTES, results), PACKED_BYTES, path)
    except FileNotFoundError:
        return []
    except OSError as error:
        raise FileRefused(path, f"cannot be read ({error.strerror or error})") from None
    lines = []
    for number, line in enumerate(data.splitlines(), 1):
        if len(line) > LINE_BYTES:
            raise FileRefused(path, f"has a line ({number}) longer than the {LINE_BYTES} bytes "
                              "a packed line may hold")
        try:
            lines.append(json.loads(line))
        except ValueError as error:
            raise FileRefused(path, f"has a line ({number}) that is not JSON ({error})"
                              ) from None
        if not isinstance(lines[-1], dict):
            raise FileRefused(path, f"has a line ({number}) that is not a JSON object")
    return lines


def read_packed(results: Path) -> Packed:
    """The packed runs of ``results`` (nothing when it has no compact files).

    Raises:
        FileRefused: a compact file that cannot be read as one (:func:`_read_lines`), or whose
            lines are not what :func:`pack` writes, naming the file.
    """
    parts = []
    for name, read in ((REPORTS_FILE, reports_of), (CONFIGS_FILE, configs_of)):
        lines = _read_lines(results / name, results)
        try:
            parts.append(read(lines) if lines else {})
        except (KeyError, TypeError, ValueError, AttributeError, StopIteration,
                yaml.YAMLError, OmegaConfBaseException) as error:
            raise FileRefused(results / name, "does not hold what armeta-reproduce packs "
                              f"({type(error).__name__}: {' '.join(str(error).split())[:80]})"
                              ) from None
    return Packed(*parts)


def pack(results: Path, packed: Packed) -> Packed:
    """Write ``packed`` as the compact files of ``results``, checked to read back equal; the
    runs now packed. The caller chooses what to pack (``armeta-reproduce``: the packed runs and
    every report and config of its run directories that its plan accepts); the run directories
    are left as they are."""
    _write_lines(results / REPORTS_FILE, report_lines(packed.reports))
    _write_lines(results / CONFIGS_FILE, config_lines(packed.configs))
    again = read_packed(results)
    if json.dumps(sorted(again.reports.items())) != json.dumps(sorted(packed.reports.items())) \
            or again.configs != packed.configs:
        raise ValueError(f"the compact files of {results} do not read back as the runs' files")
    return packed


def unpack(results: Path, packed: Packed) -> list[Path]:
    """Write every packed report and ``config.yaml`` that its run directory lacks, as the run
    wrote it; the files written."""
    written = []
    files = {**{(run, CONFIG_FILE): text for run, text in packed.configs.items()},
             **{place: json.dumps(report, indent=2) + "\n"
                for place, report in packed.reports.items()}}
    for (run, name), text in sorted(files.items()):
        path = results / run / name
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            write_text_atomically(path, text)
            written.append(path)
    return written
