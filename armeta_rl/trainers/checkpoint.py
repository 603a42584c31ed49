"""Run checkpoints through ``torchrl.checkpoint``: leader, principle, RNG state and iteration."""

from __future__ import annotations

from pathlib import Path

from torchrl.checkpoint import Checkpoint, CheckpointError, CheckpointRotation, GlobalRNGState

from armeta_rl.errors import ConfigError
from armeta_rl.learners.base import Leader
from armeta_rl.risk.base import RiskPrinciple


class RunCheckpoint:
    """Saves and restores everything a run needs to continue bit-for-bit.

    Components: the leader (parameters and optimizer), the risk principle (adversary, its
    optimizer and scheduler, group weights), the process-global RNG states and the number of
    completed iterations. Payloads are TensorDict directories, loadable without pickle.
    """

    def __init__(
        self, directory: str | Path, leader: Leader, principle: RiskPrinciple, keep_last: int = 2
    ) -> None:
        self.progress = {"iteration": 0}
        self.checkpoint = Checkpoint(
            leader=leader, principle=principle, rng=GlobalRNGState(), progress=self.progress
        )
        self.rotation = CheckpointRotation(directory, keep_last=keep_last)

    def save(self, iteration: int) -> Path:
        """Write a checkpoint after ``iteration`` completed iterations."""
        self.progress["iteration"] = iteration
        return self.rotation.save(self.checkpoint, step=iteration)

    def latest(self) -> Path | None:
        """The newest checkpoint on disk, if any."""
        return self.rotation.latest()

    def restore(self, key: str, components: tuple[str, ...] | None = None) -> int:
        """Load the newest checkpoint (all components, or ``components``); returns its iteration.

        Raises:
            ConfigError: naming ``key`` (the option that pointed at the run) if the checkpoint does
                not fit the players built from the run's config, e.g. a run saved by a version of
                armeta_rl whose defaults built other networks.
        """
        try:
            self.rotation.load_latest(self.checkpoint, components=components)
        except CheckpointError as error:
            raise ConfigError(
                key, str(self.rotation.directory.parent),
                f"its checkpoint does not fit the players its config.yaml builds ({error}); runs "
                "saved before one spline coupling became the default on 2-D boxes need "
                "'layers: 2' under risk.ar.flow_kwargs there",
            ) from error
        return int(self.progress["iteration"])
