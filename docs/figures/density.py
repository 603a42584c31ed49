"""The density figure of the README and the docs' home page (``docs/figures/density.png``): the
adversary p_φ that the default run learns, beside p0.

The default run is ``armeta-train`` with no overrides: AR-MAML on sinusoid regression, seed 0,
4000 meta-iterations. Runs are deterministic on one machine, so the figure is that run's, redrawn
by this script whenever the default run changes:

    python docs/figures/density.py                  # train the default run, then draw it
    python docs/figures/density.py --run <dir>      # draw a finished default run
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from armeta_rl.cli import train
from armeta_rl.errors import ConfigError
from armeta_rl.plots import plot_density
from armeta_rl.trainers.players import load_players

FIGURE = Path(__file__).resolve().parent / "density.png"
DEFAULT_RUN = {"benchmark": "sinusoid_uniform", "method": "ar_maml", "seed": 0,
               "iterations": 4000}
"""What identifies the default run in a run's config."""


def draw(run: Path, out: Path = FIGURE, check_default: bool = True) -> Path:
    """Draw the final p_φ of the finished run ``run`` beside its p0 into ``out``; with
    ``check_default``, refuse (ConfigError) a run that is not the default run."""
    config, players = load_players(run, "run")
    found = {"benchmark": config.benchmark.name, "method": config.method.name,
             "seed": config.seed, "iterations": config.trainer.iterations}
    if check_default and found != DEFAULT_RUN:
        raise ConfigError("run", str(run), f"is not the default run {DEFAULT_RUN}: {found}")
    if players.adversary is None:
        raise ConfigError("run", str(run), "has no adversary (an ar_* method draws one)")
    plot_density(players.adversary, players.initial, out,
                 title=f"p_φ of the default run ({found['method']}, {found['benchmark']}, "
                       f"{found['iterations']} iterations) beside p0")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, help="a finished default run (default: train one)")
    parser.add_argument("--out", type=Path, default=FIGURE, help="the PNG to write")
    args = parser.parse_args(argv)
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
