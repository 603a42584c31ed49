"""The adversary visible while it trains: p_φ's density every N meta-iterations.

:class:`DensityFrames` is the callback :class:`~armeta_rl.trainers.game.GameTrainer` calls after
every iteration. Every ``every`` iterations it draws p_φ against p0
(:func:`armeta_rl.plots.draw_density`: a curve, a heat map, or pairwise marginals for three or
more identifiers) into ``<run>/density/iter_<iteration>.png``, on the frame's own colour scale,
keeps the numbers drawn beside it (``iter_<iteration>.pt``, a
:class:`~armeta_rl.plots.DensityPicture`) and, with a logger that takes pictures (wandb,
TensorBoard, MLflow), logs the image ``adversary/density`` at that step.
:meth:`DensityFrames.finish` draws the last iteration if it is not a multiple of ``every``,
redraws every frame in the directory on one colour scale (per pair of identifiers) chosen from all
of them, and writes ``<run>/density.gif`` (logged as ``adversary/density_animation``: a wandb
video, an MLflow artifact): p0 keeps its colour from frame to frame (a resumed run's animation
includes the frames written before the interruption). Frames, their numbers and the GIF are
written atomically; a frame that cannot be read (a file damaged outside the run) is left out of
the GIF with a warning.

Drawing evaluates the exact density on a grid: it draws no random numbers, so a run with frames
is bit-identical to one without.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import torch
from matplotlib.colors import Normalize
from torchrl.record.loggers import Logger

from armeta_rl.plots import (
    DensityPicture,
    density_picture,
    draw_density,
    picture_norms,
    read_image,
    write_animation,
)
from armeta_rl.tasks.distributions import TaskDistribution
from armeta_rl.trainers.checkpoint import load_tensors, write_file
from armeta_rl.trainers.loggers import log_animation, log_picture
from armeta_rl.trainers.run_dir import write_atomically

log = logging.getLogger(__name__)

FRAMES_DIR = "density"
ANIMATION_FILE = "density.gif"
PICTURE_KEY = "adversary/density"
"""The logger key of every frame (and of the final ``density.png``)."""
ANIMATION_KEY = "adversary/density_animation"
"""The logger key of the animation of every frame, logged when the run finishes."""


class DensityFrames:
    """Draws p_φ every ``every`` iterations into ``run_dir / "density"`` (see module docstring).

    Args:
        adversary: p_φ.
        initial: p0, drawn beside it.
        run_dir: the run directory.
        every: iterations between frames (``trainer.density_every``, >= 1).
        logger: the run's logger; one that takes pictures gets each frame
            (:func:`~armeta_rl.trainers.loggers.log_picture`) and the animation.
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
        """Draw p_φ as it is now as the frame of ``iteration``, keeping its numbers beside it;
        returns the PNG's path."""
        self.frames_dir.mkdir(parents=True, exist_ok=True)
        path = self.frame_path(iteration)
        picture = density_picture(self.adversary, self.initial, self.points_per_axis)
        numbers = io.BytesIO()
        torch.save(picture.state_dict(), numbers)  # in memory: a file size limit is an OSError
        write_atomically(path.with_suffix(".pt"),
                         lambda staged: write_file(staged, numbers.getvalue()))
        self._draw(picture, iteration)
        log_picture(self.logger, PICTURE_KEY, path, iteration)
        return path

    def _draw(self, picture: DensityPicture, iteration: int, norms=None) -> Path:
        space = self.adversary.space
        path = self.frame_path(iteration)
        write_atomically(path, lambda staged: draw_density(
            picture, staged, f"p_φ at meta-iteration {iteration}", norms, space.low, space.high))
        return path

    def finish(self, iteration: int) -> Path:
        """Draw the final ``iteration`` if it has no frame yet, redraw every frame on the colour
        scales of all of them (:func:`~armeta_rl.plots.picture_norms`), then write the GIF of
        every frame in the directory, in iteration order; returns the GIF's path.

        A readable frame whose own scales are those of all frames is not drawn again: it would
        come out the same (curves have no scale; nor did any earlier set of these frames have
        other scales, as each scale only widens with the frames it covers)."""
        if not readable(self.frame_path(iteration)):
            self.draw(iteration)
        frames = sorted(self.frames_dir.glob("iter_*.png"), key=lambda f: int(f.stem[5:]))
        pictures = [self._picture(frame) for frame in frames]
        if all(picture is not None for picture in pictures):
            norms = picture_norms(pictures)
            for frame, picture in zip(frames, pictures, strict=True):
                if not (same_scales(picture_norms([picture]), norms) and readable(frame)):
                    self._draw(picture, int(frame.stem[5:]), norms)
        kept = []
        for frame in frames:
            if readable(frame):
                kept.append(frame)
            else:
                log.warning("density frame %s cannot be read: left out of %s", frame,
                            self.animation.name)
        write_atomically(self.animation, lambda staged: write_animation(kept, staged))
        log_animation(self.logger, ANIMATION_KEY, self.animation, iteration)
        return self.animation

    @staticmethod
    def _picture(frame: Path) -> DensityPicture | None:
        """The numbers drawn in ``frame``, or ``None`` when they are missing or unreadable (a run
        killed while saving them): the animation then keeps every frame's own scale."""
        try:
            return DensityPicture.from_state_dict(
                load_tensors(frame.with_suffix(".pt"), None, frame.parent))
        except (OSError, KeyError, TypeError, ValueError, RuntimeError):
            return None


def same_scales(these: dict[tuple[int, int], Normalize],
                those: dict[tuple[int, int], Normalize]) -> bool:
    """Whether two pictures' colour scales per pair (:func:`~armeta_rl.plots.picture_norms`)
    draw alike: the same kind of scale over the same range for every pair."""
    def drawn(norm: Normalize) -> tuple:
        return type(norm), norm.vmin, norm.vmax, norm.clip

    return these.keys() == those.keys() and all(drawn(these[pair]) == drawn(those[pair])
                                                 for pair in these)


def readable(frame: Path) -> bool:
    """Whether ``frame`` is a PNG that can be read back (:func:`~armeta_rl.plots.read_image`:
    e.g. not a 0-byte file, nor a link or a pipe)."""
    try:
        read_image(frame)
    except (OSError, SyntaxError, ValueError):
        return False
    return True
