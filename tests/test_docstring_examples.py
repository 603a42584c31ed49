"""Every public class and function the API reference renders (the ``:::`` entries of
docs/api/*.md) has an ``Examples:`` block of ``>>>`` lines in its docstring; pytest runs them
(``--doctest-modules`` over ``armeta_rl``, pyproject.toml)."""

import importlib
import importlib.util
import inspect
import re
from pathlib import Path

API_PAGES = Path(__file__).resolve().parents[1] / "docs" / "api"


def rendered_objects() -> dict[str, object]:
    """Dotted name → every class and function the API pages render: a package entry renders the
    names of its ``__all__``, a module entry the public ones it defines, an object entry itself."""
    objects = {}
    for page in sorted(API_PAGES.glob("*.md")):
        for entry in re.findall(r"^::: (\S+)", page.read_text(), re.M):
            parent, _, leaf = entry.rpartition(".")
            if not importlib.util.find_spec(parent).submodule_search_locations and leaf in vars(
                    importlib.import_module(parent)):
                objects[entry] = getattr(importlib.import_module(parent), leaf)
                continue
            module = importlib.import_module(entry)
            names = getattr(module, "__all__", None) or [
                name for name, value in vars(module).items()
                if not name.startswith("_") and getattr(value, "__module__", None) == entry]
            for name in names:
                value = getattr(module, name)
                if inspect.isclass(value) or inspect.isfunction(value):
                    objects[f"{entry}.{name}"] = value
    return objects


def test_the_api_pages_render_the_package():
    objects = rendered_objects()
    assert "armeta_rl.tasks.TaskSpace" in objects  # from a package's __all__
    assert "armeta_rl.rl.trpo.conjugate_gradient" in objects  # defined in a module entry
    assert "armeta_rl.rl.trpo.episode_mean" not in objects  # imported there, rendered elsewhere


def test_every_rendered_object_has_a_runnable_example():
    missing = [name for name, value in rendered_objects().items()
               if not re.search(r"^\s*Examples:\s*\n\s*>>> ", inspect.getdoc(value) or "", re.M)]
    assert not missing, f"no Examples block with >>> lines: {', '.join(missing)}"
