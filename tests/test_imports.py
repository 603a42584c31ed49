"""Importing the package and the CLI's module loads no heavy dependency, and the modules that
declare, register and check the learners' options import in any order."""

from __future__ import annotations

import subprocess
import sys

import pytest

HEAVY = ("torch", "ray", "mujoco", "warp", "matplotlib", "wandb")


def imported_after(statement: str) -> set[str]:
    """The top-level packages a fresh interpreter holds after running ``statement`` (which must
    succeed)."""
    code = f"{statement}\nimport sys\nprint(' '.join({{m.split('.')[0] for m in sys.modules}}))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr
    return set(result.stdout.split())


@pytest.mark.parametrize("statement", ["import armeta_rl", "from armeta_rl.cli import train"])
def test_the_package_and_the_cli_module_import_no_heavy_dependency(statement: str) -> None:
    assert imported_after(statement).isdisjoint(HEAVY)


@pytest.mark.parametrize(
    "module", ["armeta_rl.factory", "armeta_rl.learners.cnp", "armeta_rl.risk.tail"]
)
def test_the_learner_registry_imports_whichever_module_comes_first(module: str) -> None:
    """config derives its learner schema from factory's registry, whose learners declare their
    options with armeta_rl.fields: entered from any of them, every learner is registered."""
    statement = (f"import {module}\nimport armeta_rl.config as config\n"
                 "assert sorted(config.learner_sections()) == "
                 "['anil', 'cnp', 'maml', 'maml_ppo', 'maml_trpo']")
    imported_after(statement)
