"""The package's modules import each other without a circle: every ``armeta_rl`` module reaches
only modules below it. Every import statement counts, wherever it stands in a module: an import
inside a function defers a circle to the call, it does not remove it."""

import ast
import graphlib
from pathlib import Path

import armeta_rl

PACKAGE = Path(armeta_rl.__file__).parent


def module_files() -> dict[str, Path]:
    """Dotted name → file of every module of the package (a package is its ``__init__.py``)."""
    files = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return files


def imported(node: ast.AST, modules: dict[str, Path]) -> list[str]:
    """The package's modules an import statement names (``from a.b import c``: ``a.b.c`` where
    that is a module, else ``a.b``); none for any other node."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
        names = [f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in modules
                 else node.module for alias in node.names]
    else:
        return []
    found = []
    for name in names:
        while name not in modules and "." in name:
            name = name.rsplit(".", 1)[0]
        if name in modules:
            found.append(name)
    return found


def packages_run_first(target: str, importer: str) -> set[str]:
    """The packages whose ``__init__`` runs when ``importer`` imports ``target``: those above
    ``target``, but the package root (every module is under it) and the packages above
    ``importer`` (they are already being imported)."""
    def above(name: str) -> set[str]:
        parts = name.split(".")
        return {".".join(parts[:i]) for i in range(2, len(parts))}

    return above(target) - above(importer) - {importer}


def import_graph() -> dict[str, set[str]]:
    """Module → the package's modules it imports, at module level or inside a function, with
    the packages whose ``__init__`` such an import runs first."""
    modules = module_files()
    graph = {}
    for name, path in modules.items():
        targets = {target for node in ast.walk(ast.parse(path.read_text()))
                   for target in imported(node, modules) if target != name}
        graph[name] = targets.union(*(packages_run_first(t, name) for t in targets))
    return graph


def test_the_graph_holds_module_level_and_function_level_imports():
    graph = import_graph()
    assert "armeta_rl.config_files" in graph["armeta_rl.tasks.shifts"]  # module level
    assert "armeta_rl.trainers.training" in graph["armeta_rl.cli.jobs"]  # inside a function
    assert "armeta_rl.tasks.transform" in graph["armeta_rl.tasks"]  # a package's __init__
    # importing armeta_rl.adversary.flow_adversary runs armeta_rl/adversary/__init__.py first
    assert "armeta_rl.adversary" in graph["armeta_rl.risk.adversarial"]
    assert packages_run_first("armeta_rl.tasks.shifts", "armeta_rl.tasks.transform") == set()


def test_no_import_circle():
    try:
        order = list(graphlib.TopologicalSorter(import_graph()).static_order())
    except graphlib.CycleError as error:
        circle = " imports ".join(reversed(error.args[1]))
        raise AssertionError(f"import circle: {circle}") from None
    assert order.index("armeta_rl.config_files") < order.index("armeta_rl.cli")
