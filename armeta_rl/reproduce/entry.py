"""``armeta-reproduce``'s entry point: ``--help`` answered from the package's files (no torch, no
Ray), every other command line by :func:`armeta_rl.reproduce.cli.main`."""

from __future__ import annotations

import sys

from armeta_rl.reproduce import help_text


def main() -> None:
    """``armeta-reproduce``: ``--help`` answered here, every other command line by
    :func:`armeta_rl.reproduce.cli.main`."""
    if any(arg in ("--help", "-h") for arg in sys.argv[1:]):
        print(help_text())
        sys.exit(0)
    from armeta_rl.reproduce.cli import main as run

    run()
