"""``hydra/sweeper=run_list``: launch the jobs listed in a YAML file, each its own override list.

Hydra's basic sweeper launches the cartesian product of comma-separated values. An experiment of
the paper is not one product (its benchmarks take different overrides, finished runs are left
out), so ``armeta-reproduce`` writes the override list of every job it still needs into a file
and hands it to this sweeper, which passes the lists unchanged to the configured launcher
(``hydra/launcher=joblib``, ``ray``, ``submitit_slurm``, …). Each job is composed and run exactly
as ``armeta-train <overrides>`` typed by hand would be.

The file holds ``{"jobs": [{"name": ..., "overrides": [...], "done": <path>}, ...]}``; ``done`` is
the file the job writes when it finishes (read by :class:`armeta_rl.reproduce.progress.Progress`).
Unlike the basic sweeper it does not compose every job before launching (that doubles the
composition time of a large sweep): ``armeta-reproduce`` checks each distinct run config first,
and the launcher composes each job as it runs it.

Every job runs even when some fail: a job's user error comes back as
:class:`armeta_rl.errors.JobFailed`, and the sweep then exits with the highest code among them.
"""

# No `from __future__ import annotations`: Hydra loads plugin modules without registering them in
# sys.modules, and dataclasses cannot then resolve string annotations.
import io
from contextlib import redirect_stderr
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.core.plugins import Plugins
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf

from armeta_rl.errors import JobFailed
from armeta_rl.reproduce import read_jobs


@dataclass
class RunListSweeperConf:
    _target_: str = "hydra_plugins.armeta_run_list.run_list_sweeper.RunListSweeper"
    jobs_file: str = "???"


ConfigStore.instance().store(
    group="hydra/sweeper", name="run_list", node=RunListSweeperConf, provider="armeta_rl"
)


class RunListSweeper(Sweeper):
    """Launch every job of ``jobs_file`` (command-line overrides first, then the job's own)."""

    def __init__(self, jobs_file: str) -> None:
        self.jobs_file = jobs_file
        self.config: DictConfig | None = None
        self.launcher = None

    def setup(
        self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig
    ) -> None:
        self.config = config
        self.hydra_context = hydra_context
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def sweep(self, arguments: list[str]) -> Any:
        batch = [[*arguments, *job["overrides"]] for job in read_jobs(self.jobs_file)]
        sweep_dir = Path(self.config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")
        returns = self.launcher.launch(batch, initial_job_idx=0)
        codes = []
        for result in returns:
            try:  # re-raises a job's exception, as the basic sweeper does, after a line of
                with redirect_stderr(io.StringIO()):  # Hydra's that would repeat the job's own
                    _ = result.return_value
            except JobFailed as failed:  # its one line is printed; the other jobs ran
                codes.append(failed.code)
        if codes:
            raise SystemExit(max(codes))
        return returns
