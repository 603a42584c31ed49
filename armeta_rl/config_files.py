"""Where the YAML config files are, for every module that reads one: the CLI composes from them,
:mod:`armeta_rl.tasks.shifts` reads the shift suites and :mod:`armeta_rl.reproduce.plan` the
experiments. It imports nothing of the package, so a module on any floor reads config files
without reaching up to the CLI.
"""

from __future__ import annotations

from pathlib import Path


def config_files() -> Path:
    """Where the config files are: packaged in a wheel, or the repository's ``configs/``.

    Examples:
        >>> from armeta_rl.config_files import config_files
        >>> (config_files() / "train.yaml").is_file()
        True
    """
    packaged = Path(__file__).parent / "configs"
    return packaged if packaged.is_dir() else Path(__file__).resolve().parents[1] / "configs"


def group_choices(group: str) -> list[str]:
    """Names of the configs available for a config group, e.g. the benchmarks.

    Examples:
        >>> from armeta_rl.config_files import group_choices
        >>> "point_nav" in group_choices("benchmark")
        True
    """
    return sorted(path.stem for path in (config_files() / group).glob("*.yaml"))
