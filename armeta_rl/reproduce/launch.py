"""Launching a plan's jobs as Hydra multiruns of the ordinary entry points.

The training runs are one ``armeta-train -m`` sweep, the attack runs (which need their targets
finished) a second one and the cross-evaluations one ``armeta-eval -m`` sweep, each with
``hydra/sweeper=run_list`` (the jobs file lists each job's overrides) and the chosen Hydra
launcher: joblib processes on this machine, tasks on a Ray cluster, or Slurm jobs
through submitit. Each job is composed and run exactly as the same command typed by hand.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

from omegaconf import OmegaConf

from armeta_rl.errors import ConfigError
from armeta_rl.reproduce.plan import EvalJob, TrainRun, interrupted

LAUNCHERS = ("local", "basic", "ray", "slurm", "none")
"""``local``: joblib processes on this machine (``jobs=`` of them, default all cores);
``basic``: one job after the other in this process; ``ray``: Ray tasks (the cluster of
``RAY_ADDRESS`` or ``hydra.launcher.ray.init.address=``, else a new local one); ``slurm``:
submitit's Slurm launcher (``hydra.launcher.partition=`` etc.); ``none``: launch nothing, only
aggregate what has finished (e.g. while a sweep runs elsewhere)."""


def launcher_overrides(launcher: str, jobs: int | None) -> list[str]:
    """The Hydra overrides that select ``launcher`` (``jobs``: parallel jobs of ``local``)."""
    if launcher == "local":
        return ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs or -1}"]
    if launcher in ("basic", "none"):
        return []
    if launcher == "ray":
        return ["hydra/launcher=ray"]
    if launcher == "slurm":
        return ["hydra/launcher=submitit_slurm"]
    raise ConfigError("launcher", launcher, f"allowed: {', '.join(LAUNCHERS)}")


def train_job(results: Path, run: TrainRun) -> dict:
    """The sweeper's entry for ``run``: its overrides, or ``resume=`` for an interrupted run (its
    directory holds its config): it continues from its last checkpoint, or starts again from the
    beginning if it had written none, bit-identical to an uninterrupted run either way."""
    overrides = ([f"resume={results / run.subdir}"] if interrupted(results, run)
                 else run.command(results))
    return {"name": run.subdir, "overrides": [*overrides, f"hydra.sweep.subdir={run.subdir}"],
            "done": str(results / run.subdir / "eval.json")}


def eval_job(results: Path, job: EvalJob) -> dict:
    """The sweeper's entry for an ``armeta-eval`` job."""
    return {"name": job.out, "overrides": [*job.command(results),
                                           f"hydra.sweep.subdir={job.learner.subdir}"],
            "done": str(results / job.out)}


def launch(entry: Callable[[list[str]], int], jobs: Sequence[dict], results: Path,
           label: str, finished_before: int, hydra_args: Sequence[str]) -> int:
    """Run ``jobs`` as one multirun of ``entry`` (``armeta_rl.cli.train`` or ``evaluate``, which
    take the command line's arguments) and return its exit code (0 when every job finished).

    The jobs file goes to ``results/.sweeps/<label>.yaml`` (kept: it records what was launched).
    """
    jobs_file = results / ".sweeps" / f"{label.replace(' ', '-')}.yaml"
    jobs_file.parent.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(OmegaConf.create({"jobs": list(jobs)}), jobs_file)
    progress = "+hydra.callbacks.progress"
    argv = ["-m", "hydra/sweeper=run_list", f"hydra.sweeper.jobs_file={jobs_file}",
            f"hydra.sweep.dir={results}",
            f"{progress}._target_=armeta_rl.reproduce.progress.Progress",
            f"{progress}.jobs_file={jobs_file}", f"{progress}.label={label}",
            f"{progress}.started={time.time()}", f"{progress}.finished_before={finished_before}",
            *hydra_args]
    return entry(argv)
