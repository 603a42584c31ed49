"""Wall time of ``--help`` of the three console scripts, each a fresh process as a user runs it,
and which heavy packages (torch, TorchRL, MuJoCo, Ray) answering it imports: help reads only the
config folder (``armeta_rl.cli._print_help``, ``armeta_rl.reproduce.help_text``)."""

from __future__ import annotations

import shutil
import statistics
import subprocess
import sys

from timing import markdown_table, wall_times, write_section

COMMANDS = ("armeta-train", "armeta-eval", "armeta-reproduce")
HEAVY = ("torch", "torchrl", "mujoco", "ray")
REPEATS = 7
PROBE = """
import sys
from importlib.metadata import entry_points
(script,) = [e for e in entry_points(group="console_scripts") if e.name == sys.argv[1]]
sys.argv = [sys.argv[1], "--help"]
try:
    script.load()()
except SystemExit:
    pass
print(",".join(p for p in {heavy} if p in sys.modules) or "none", file=sys.stderr)
"""


def heavy_imports(command: str) -> str:
    """The heavy packages in ``sys.modules`` once ``command --help`` has answered."""
    probe = PROBE.format(heavy=HEAVY)
    done = subprocess.run([sys.executable, "-c", probe, command], capture_output=True, text=True,
                          check=True)
    return done.stderr.strip().splitlines()[-1]


def main() -> None:
    rows = []
    for command in COMMANDS:
        path = shutil.which(command)
        times = wall_times(lambda p=path: subprocess.run([p, "--help"], check=True,
                                                         capture_output=True), REPEATS)
        rows.append((f"`{command} --help`", f"{statistics.median(times):.2f}",
                     f"{max(times):.2f}", heavy_imports(command)))
    body = (f"Each command's `--help` in a fresh process (wall seconds, median and slowest of "
            f"{REPEATS}, after one untimed run), and the heavy packages it imported:\n\n"
            + markdown_table(("command", "median s", "slowest s", "imports"), rows))
    print(body)
    write_section("bench_help", "Console scripts' help (bench_help.py)", body)


if __name__ == "__main__":
    main()
