"""``armeta-reproduce``'s entry point: ``--help`` answered from the package's files (no torch, no
Ray), an address-space limit too small to load torch refused in one line, every other command
line by :func:`armeta_rl.reproduce.cli.main`."""

from __future__ import annotations

import sys

from armeta_rl.cli.failures import address_space_refusal
from armeta_rl.reproduce import help_text


def main() -> None:
    """``armeta-reproduce``: ``--help`` and an address-space limit below
    :data:`~armeta_rl.cli.failures.ADDRESS_SPACE_FLOOR` answered here, every other command line
    by :func:`armeta_rl.reproduce.cli.main`."""
    if any(arg in ("--help", "-h") for arg in sys.argv[1:]):
        print(help_text())
        sys.exit(0)
    refusal = address_space_refusal()
    if refusal is not None:
        print(f"armeta-reproduce: error: {refusal}", file=sys.stderr)
        sys.exit(2)
    from armeta_rl.reproduce.cli import main as run

    run()
