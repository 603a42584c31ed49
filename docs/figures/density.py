"""The density figure of the README and the docs' home page (``docs/figures/density.png``): the
adversary p_φ that the default run learns, beside p0.

The default run is ``armeta-train`` with no overrides: AR-MAML on sinusoid regression, seed 0,
4000 meta-iterations. Runs are deterministic on one machine, but another CPU rounds differently
and learns a slightly different p_φ, so the figure names the command and the machine that drew
it, and the numbers it shows are committed beside it (``density.pt``, a
:class:`~armeta_rl.plots.DensityPicture`; ``density.json``: command, machine, date): the figure
is redrawn from them on any machine.

    python docs/figures/density.py                  # train the default run, then draw it
    python docs/figures/density.py --run <dir>      # draw a finished default run
    python docs/figures/density.py --redraw         # redraw from the committed numbers
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

import torch

from armeta_rl.cli import train
from armeta_rl.devices import cpu_model
from armeta_rl.errors import ConfigError
from armeta_rl.plots import DensityPicture, density_picture, draw_density
from armeta_rl.trainers.players import load_players

HERE = Path(__file__).resolve().parent
FIGURE, NUMBERS, PROVENANCE = HERE / "density.png", HERE / "density.pt", HERE / "density.json"
COMMAND = "armeta-train (the default run), drawn by python docs/figures/density.py"
POINTS = 60
"""Grid points per identifier: the heat maps' resolution and the size of ``density.pt``."""
DEFAULT_RUN = {"benchmark": "sinusoid_uniform", "method": "ar_maml", "seed": 0,
               "iterations": 4000}
"""What identifies the default run in a run's config."""


def this_machine() -> str:
    """The CPU model, its logical CPUs, the OS and torch: what sets a run's rounding."""
    return (f"{cpu_model()}, {os.cpu_count()} logical CPUs, {platform.system()}, "
            f"torch {torch.__version__}")


def draw(run: Path, out: Path = FIGURE, check_default: bool = True, numbers: Path = NUMBERS,
         provenance: Path = PROVENANCE) -> Path:
    """Draw the final p_φ of the finished run ``run`` beside its p0: its numbers into
    ``numbers``, the command and this machine into ``provenance``, the figure into ``out``; with
    ``check_default``, refuse (ConfigError) a run that is not the default run."""
    config, players = load_players(run, "run")
    found = {"benchmark": config.benchmark.name, "method": config.method.name,
             "seed": config.seed, "iterations": config.trainer.iterations}
    if check_default and found != DEFAULT_RUN:
        raise ConfigError("run", str(run), f"is not the default run {DEFAULT_RUN}: {found}")
    if players.adversary is None:
        raise ConfigError("run", str(run), "has no adversary (an ar_* method draws one)")
    picture = density_picture(players.adversary, players.initial, POINTS)
    state = picture.state_dict()
    torch.save({k: v.float() if isinstance(v, torch.Tensor) else v for k, v in state.items()},
               numbers)
    provenance.write_text(json.dumps({
        "run": found, "command": COMMAND, "machine": this_machine(),
        "date": datetime.date.today().isoformat(),
        "box": {"low": list(players.adversary.space.low),
                "high": list(players.adversary.space.high)}}, indent=2) + "\n")
    return redraw(out, numbers, provenance)


def redraw(out: Path = FIGURE, numbers: Path = NUMBERS, provenance: Path = PROVENANCE) -> Path:
    """Draw the figure from the committed numbers and provenance: the same picture on any
    machine, titled with the run, the command and the machine that computed it."""
    picture = DensityPicture.from_state_dict(torch.load(numbers, weights_only=True))
    about = json.loads(provenance.read_text())
    run = about["run"]
    title = (f"p_φ of the default run ({run['method']}, {run['benchmark']}, {run['iterations']} "
             f"iterations) beside p0\n{about['command']}\non {about['machine']}, "
             f"{about['date']}")
    draw_density(picture, out, title, low=about["box"]["low"], high=about["box"]["high"])
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, help="a finished default run (default: train one)")
    parser.add_argument("--redraw", action="store_true",
                        help="redraw from the committed numbers, training nothing")
    parser.add_argument("--out", type=Path, default=FIGURE, help="the PNG to write")
    args = parser.parse_args(argv)
    if args.redraw:
        print(redraw(args.out))
        return 0
    run = args.run
    if run is None:
        run = Path(tempfile.mkdtemp(prefix="default-run-")) / "run"
        code = train([f"hydra.run.dir={run}", "trainer.progress=false", "logger=none"])
        if code:
            return code
    try:
        print(draw(run, args.out))
    except ConfigError as error:
        print(f"density.py: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
