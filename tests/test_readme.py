"""The README's Python examples run as written."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"
PYTHON_BLOCK = r"```python\n(.*?)```"


def test_readme_python_examples_run():
    blocks = re.findall(PYTHON_BLOCK, README.read_text(), flags=re.S)
    assert blocks
    for block in blocks:
        exec(compile(block, str(README), "exec"), {})


def test_own_code_example_uses_the_task_key_and_runs():
    """"Using the pieces in your own code": sample from p_φ, reset an env with the samples under
    the one task key, roll out; the identifiers persist (its own assert) under a transform."""
    section = README.read_text().split("## Using the pieces in your own code", 1)[1]
    block = re.search(PYTHON_BLOCK, section.split("\n## ", 1)[0], flags=re.S).group(1)
    assert "TASK_KEY" in block and '"params"' not in block.replace('(= "params")', "")
    namespace: dict = {}
    exec(compile(block, str(README), "exec"), namespace)
    assert namespace["rollout"].batch_size == (16, 4, 200)
