"""A training run as its entry resolves it: the checked config, the run directory and, for a
resumed run, the config the run saved. The CLI makes one per run
(:func:`armeta_rl.cli.jobs.make_job`: from a command line, a sweep job's composed config or a
resume directory), and :func:`armeta_rl.trainers.training.run_training` trains it without
reading a config from disk."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from armeta_rl.config import TrainConfig


@dataclass(frozen=True)
class Job:
    """One run to train.

    ``config``: the validated config (:func:`armeta_rl.config.validate`). ``run_dir``: where the
    run writes. ``saved``: a resumed run's saved config, resolved, as plain YAML types (what its
    ``config.yaml`` holds, rewritten with the new ``trainer.iterations`` when it trains longer);
    ``None`` for a new run. ``taken``: ``key=value`` of each key a resume changed that changes no
    result, said as it starts. A new run from Python is ``Job(config, run_dir)``; a resumed one
    comes from :func:`armeta_rl.cli.jobs.make_job`, which reads its saved config.
    """

    config: TrainConfig
    run_dir: Path
    saved: dict[str, Any] | None = None
    taken: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if (self.config.resume is None) != (self.saved is None):
            raise ValueError("a resumed run's Job holds the config it saved, a new run's none: "
                             "make a resumed one with armeta_rl.cli.jobs.make_job")

    @property
    def saved_iterations(self) -> int | None:
        """The resumed run's saved ``trainer.iterations`` (``None``: a new run)."""
        return None if self.saved is None else self.saved["trainer"]["iterations"]
