"""docs/torchrl.md's Python blocks run as written, one after the other, as a reader runs them: a
block with a ``__main__`` guard (a multi-process collector, whose spawned workers import the
script again) runs as a script of its own, the others in one namespace."""

import os
import re
import subprocess
import sys
from pathlib import Path

PAGE = Path(__file__).resolve().parents[1] / "docs" / "torchrl.md"


def test_the_torchrl_page_runs(tmp_path):
    blocks = re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S)
    scripts = [block for block in blocks if 'if __name__ == "__main__":' in block]
    assert len(blocks) >= 6 and len(scripts) == 1
    namespace: dict = {"__name__": "torchrl_docs"}
    for block in blocks:
        if block in scripts:
            script = tmp_path / "multi_process.py"
            script.write_text(block)
            env = {**os.environ, "OMP_NUM_THREADS": "1"}
            done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env,
                                  capture_output=True, text=True, timeout=600)
            assert done.returncode == 0, done.stderr[-3000:]
        else:
            exec(compile(block, str(PAGE), "exec"), namespace)
    adam = namespace["sampler"].follower.optimizer.state.values()
    assert adam and all(int(state["step"]) == 3 for state in adam)  # one step per batch
    assert namespace["per_task"].batch_size == (5,)
    assert namespace["scalars"]["ppo_objective_last"] < namespace["scalars"]["ppo_objective_first"]
