"""A finished (or checkpointed) run directory in one call: its config, its players with the latest
checkpoint, and its evaluation reports (:func:`load_run`, also ``armeta_rl.load_run``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from armeta_rl.config import TrainConfig
from armeta_rl.errors import ConfigError
from armeta_rl.learners.base import Leader
from armeta_rl.tasks import TaskDistribution
from armeta_rl.trainers.evaluation import ReportInvalid, read_report
from armeta_rl.trainers.players import Players, load_players
from armeta_rl.trainers.report import EVAL_FILE


@dataclass
class Run:
    """A run directory, loaded: where it is, its config, its players (the leader θ, the
    principle with its adversary p_φ where it has one, p0, the task box, the evaluation
    collector) with its latest checkpoint, and its reports by file stem (``"eval"``: the run's
    own ``eval.json``; ``"eval_vs_<run>"``, ``"eval_shifts"``: ``armeta-eval``'s).

    :func:`load_run` gives one from a run directory; the example builds one from a config
    instead, its players untrained, to show what it holds.

    Examples:
        >>> from pathlib import Path
        >>> from hydra import compose, initialize_config_dir
        >>> from armeta_rl.config import validate
        >>> from armeta_rl.config_files import config_files
        >>> from armeta_rl.runs import Run
        >>> from armeta_rl.trainers.players import build_players
        >>> def untrained(method):
        ...     with initialize_config_dir(config_dir=str(config_files()), version_base=None):
        ...         config = validate(compose("train", overrides=[f"method={method}"]))
        ...     return Run(Path("runs", method), config, build_players(config), reports={})
        >>> run = untrained("ar_maml")
        >>> run.config.benchmark.name, type(run.leader).__name__, type(run.adversary).__name__
        ('sinusoid_uniform', 'MAMLLeader', 'FlowAdversary')
        >>> tasks = run.adversary.sample(1000)["params"]  # tasks from p_φ, in the task box
        >>> run.players.space.names, bool(run.players.space.contains(tasks).all())
        (('amplitude', 'phase'), True)
        >>> untrained("maml").adversary is None  # a method without p_φ
        True
    """

    path: Path
    config: TrainConfig
    players: Players
    reports: dict[str, dict[str, Any]]

    @property
    def leader(self) -> Leader:
        """The meta-learner θ, as last checkpointed."""
        return self.players.leader

    @property
    def adversary(self) -> TaskDistribution | None:
        """The learned task distribution p_φ (``None`` for a method without one)."""
        return self.players.adversary


def load_run(path: str | Path, device: str | None = None) -> Run:
    """The run in directory ``path``: its saved config, its players with the latest checkpoint
    loaded (as ``armeta-train resume=`` and ``armeta-eval`` load them), on ``device`` (default:
    the run's own), and its evaluation reports, each checked as a finished run's is.

    Raises:
        ConfigError: naming ``run``, where ``path`` is not a run directory, its config or
            checkpoint cannot be loaded, or a report of it fails its schema.

    Examples:
        >>> from armeta_rl import load_run
        >>> load_run("no/such/run")
        Traceback (most recent call last):
        ...
        armeta_rl.errors.ConfigError: config key 'run' = 'no/such/run': is not a run directory ...
    """
    config, players = load_players(path, "run", device)
    reports = {}
    for file in sorted(Path(path).glob("eval*.json")):
        try:
            reports[file.stem] = read_report(file, ("initial",) if file.name == EVAL_FILE else ())
        except ReportInvalid as error:
            raise ConfigError("run", str(path), f"its report {file.name} is invalid: {error}"
                              ) from None
    return Run(Path(path), config, players, reports)
