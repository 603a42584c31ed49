"""Every Python block of the docs pages and the README runs as written, warning-free (every
warning an error), the blocks of a page one after the other in one namespace as a reader runs
them. A block marked ``<!-- not run: reason -->`` on the line before it is illustration only (a
full training run, a GPU); a block with a ``__main__`` guard (a multi-process collector, whose
workers import the script again) runs as a script of its own."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torchrl.collectors  # noqa: F401  (its import-time DeprecationWarnings are TorchRL's)

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted(p for p in [ROOT / "README.md", *(ROOT / "docs").glob("*.md")]
               if "```python" in p.read_text())
BLOCK = re.compile(r"(<!-- not run: [^>]+ -->\n)?```python\n(.*?)```", flags=re.S)


def blocks(page: Path) -> list[tuple[bool, str]]:
    """``(runs, code)`` of each Python block of ``page``."""
    return [(not marker, code) for marker, code in BLOCK.findall(page.read_text())]


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_the_page_s_python_blocks_run_without_a_warning(page, tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)  # the blocks read configs/ as a reader in a checkout does
    namespace: dict = {"__name__": f"docs_{page.stem}"}
    for runs, code in blocks(page):
        if not runs:
            continue
        if 'if __name__ == "__main__":' in code:
            script = tmp_path / "script.py"
            script.write_text(code)
            env = {**os.environ, "OMP_NUM_THREADS": "1",
                   "PYTHONWARNINGS": "error::FutureWarning,error::UserWarning"}
            done = subprocess.run([sys.executable, str(script)], env=env, capture_output=True,
                                  text=True, timeout=600)
            assert done.returncode == 0, done.stderr[-3000:]
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            exec(compile(code, str(page), "exec"), namespace)
