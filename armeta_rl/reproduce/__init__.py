"""Reproducing the paper: each table or figure is an experiment declared in
``configs/reproduce/<experiment>.yaml``, run as Hydra multiruns of ``armeta-train`` and
``armeta-eval`` and aggregated into CSV, Markdown and PNG (``armeta-reproduce``,
docs/reproducing.md).
"""

from __future__ import annotations

import ast
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import yaml

from armeta_rl.config_files import config_files

PROFILES_FILE = "profiles.yaml"
"""The profiles shared by the experiments, beside them in ``configs/reproduce/``."""


def read_jobs(jobs_file: str | Path) -> list[dict[str, Any]]:
    """The jobs of a sweep's jobs file (``{"jobs": [{"name", "overrides", "done"}, ...]}``, written
    by :func:`armeta_rl.reproduce.launch.launch`), read by the ``run_list`` sweeper and by
    :class:`~armeta_rl.reproduce.progress.Progress` as each job starts and ends: plain YAML,
    read with PyYAML's C loader where it has one (an evaluation sweep's file holds hundreds of
    jobs, and OmegaConf's loader takes a quarter of a second over one)."""
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    return yaml.load(Path(jobs_file).read_text(), Loader=loader)["jobs"]


def experiment_names() -> list[str]:
    """The experiments in ``configs/reproduce/`` (every YAML but the shared profiles)."""
    folder = config_files() / "reproduce"
    return sorted(p.stem for p in folder.glob("*.yaml") if p.name != PROFILES_FILE)


def help_text() -> str:
    """``armeta-reproduce --help``: the usage (the docstring of :mod:`armeta_rl.reproduce.cli`,
    read from its source, so that help imports neither torch nor Ray) and the experiments."""
    source = Path(find_spec("armeta_rl.reproduce.cli").origin).read_text(encoding="utf-8")
    usage = ast.get_docstring(ast.parse(source)).replace("``", "").strip()
    return f"usage: {usage}\n\nexperiments: {', '.join(experiment_names())}"
