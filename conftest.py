"""Doctest collection of the package (``--doctest-modules`` over ``armeta_rl``): a module whose
optional dependency is not installed is left out, as the tests of it are skipped."""

from importlib.util import find_spec

OPTIONAL = {"armeta_rl/collectors/ray_episodes.py": "ray"}

collect_ignore = [path for path, module in OPTIONAL.items() if find_spec(module) is None]
