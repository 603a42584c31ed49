"""``--help`` of ``armeta-train`` and ``armeta-eval``."""

from __future__ import annotations

from armeta_rl.config_files import group_choices


def print_help(prog: str, config_name: str, groups: tuple[str, ...], usage: str) -> None:
    """``--help``: the usage, the groups a command line chooses from and where to see the
    composed config. It reads only the config folder: composing the config would import every
    learner (torch, TorchRL, MuJoCo) for a page of text, which ``--cfg job`` prints instead."""
    lines = [f"{prog}: {usage}", "", "Configuration groups (group=option):"]
    lines += [f"  {group}: {', '.join(group_choices(group))}" for group in groups] or ["  none"]
    lines += ["", f"Config: configs/{config_name}.yaml and the dataclasses it lists; override any "
              "key with key=value, add one with +key=value (docs/configuration.md).",
              f"The composed config of a command line, every key with its value: {prog} "
              "[overrides] --cfg job",
              "Hydra's own flags (-m, --cfg job, -sc install=bash, ...): --hydra-help"]
    print("\n".join(lines))
