"""Importing the package and the CLI's module loads no heavy dependency, the config imports no
learner, and the modules that declare and register the learners' options import in any order."""

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


def test_the_config_imports_no_learner_or_risk_principle() -> None:
    """The root schema sits below the learners: they register their sections with it."""
    imported_after("import sys, armeta_rl.config\n"
                   "assert not [m for m in sys.modules if m.startswith(('armeta_rl.learners', "
                   "'armeta_rl.risk', 'armeta_rl.factory'))]")


@pytest.mark.parametrize(
    "module", ["armeta_rl.factory", "armeta_rl.learners.cnp", "armeta_rl.risk.tail"]
)
def test_the_registry_registers_every_section_whichever_module_comes_first(module: str) -> None:
    """Entered from any module, importing the registry registers every learner's and risk
    principle's section in Hydra's ConfigStore."""
    statement = (f"import {module}\nimport armeta_rl.factory\n"
                 "from armeta_rl.config import schema\n"
                 "assert sorted(schema().learner) == "
                 "['anil', 'cnp', 'maml', 'maml_ppo', 'maml_trpo']\n"
                 "assert sorted(schema().risk) == ['ar', 'dr', 'dro', 'mpts', 'pdts', 'tr']")
    imported_after(statement)
