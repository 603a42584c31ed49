"""The adversary visible while it trains: p_φ's density every N meta-iterations.

:class:`DensityFrames` is the callback :class:`~armeta_rl.trainers.game.GameTrainer` calls after
every iteration. Every ``every`` iterations it draws p_φ against p0
(:func:`armeta_rl.plots.plot_density`: a curve, a heat map, or pairwise marginals for three or
more identifiers) into ``<run>/density/iter_<iteration>.png`` and, with a wandb logger, logs it as
the image ``adversary/density`` at that step. :meth:`DensityFrames.finish` draws the last
iteration if it is not a multiple of ``every`` and writes ``<run>/density.gif`` from all frames in
the directory (a resumed run's animation includes the frames written before the interruption).

Drawing evaluates the exact density on a grid: it draws no random numbers, so a run with frames
is bit-identical to one without.
"""

from __future__ import annotations

from pathlib import Path

from torchrl.record.loggers import Logger, WandbLogger

from armeta_rl.plots import plot_density, write_animation
from armeta_rl.tasks.distributions import TaskDistribution

FRAMES_DIR = "density"
ANIMATION_FILE = "density.gif"


class DensityFrames:
    """Draws p_φ every ``every`` iterations into ``run_dir / "density"`` (see module docstring).

    Args:
        adversary: p_φ.
        initial: p0, drawn beside it.
        run_dir: the run directory.
        every: iterations between frames (``trainer.density_every``, >= 1).
        logger: the run's logger; a :class:`~torchrl.record.loggers.WandbLogger` also gets each
            frame as an image.
        points_per_axis: grid resolution of each frame.
    """

    def __init__(self, adversary: TaskDistribution, initial: TaskDistribution, run_dir: Path,
                 every: int, logger: Logger | None = None, points_per_axis: int = 40) -> None:
        self.adversary, self.initial = adversary, initial
        self.frames_dir = Path(run_dir) / FRAMES_DIR
        self.animation = Path(run_dir) / ANIMATION_FILE
        self.every, self.logger, self.points_per_axis = every, logger, points_per_axis

    def frame_path(self, iteration: int) -> Path:
        return self.frames_dir / f"iter_{iteration:06d}.png"

    def __call__(self, iteration: int) -> None:
        """Draw the frame of ``iteration`` when it is a multiple of ``every``."""
        if iteration % self.every == 0:
            self.draw(iteration)

    def draw(self, iteration: int) -> Path:
        """Draw p_φ as it is now as the frame of ``iteration``; returns the PNG's path."""
        self.frames_dir.mkdir(parents=True, exist_ok=True)
        path = self.frame_path(iteration)
        plot_density(self.adversary, self.initial, path, self.points_per_axis,
                     title=f"p_φ at meta-iteration {iteration}")
        if isinstance(self.logger, WandbLogger):
            import wandb

            self.logger.log_metrics({"adversary/density": wandb.Image(str(path))}, iteration)
        return path

    def finish(self, iteration: int) -> Path:
        """Draw the final ``iteration`` if it has no frame yet, then write the GIF of every frame
        in the directory, in iteration order; returns the GIF's path."""
        if not self.frame_path(iteration).exists():
            self.draw(iteration)
        frames = sorted(self.frames_dir.glob("iter_*.png"), key=lambda f: int(f.stem[5:]))
        write_animation(frames, self.animation)
        return self.animation
