"""Launching a plan's jobs as Hydra multiruns of the ordinary entry points.

The training runs are one ``armeta-train -m`` sweep, the attack runs (which need their targets
finished) a second one and the cross-evaluations one ``armeta-eval -m`` sweep, each with
``hydra/sweeper=run_list`` (the jobs file lists each job's overrides) and the chosen Hydra
launcher: joblib processes on this machine, tasks on a Ray cluster, or Slurm jobs
through submitit. Each job is composed and run exactly as the same command typed by hand.
"""

from __future__ import annotations

import os
import socket
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


def ray_address(hydra_args: Sequence[str]) -> str | None:
    """The Ray cluster a ``launcher=ray`` sweep joins: ``hydra.launcher.ray.init.address=``, else
    ``RAY_ADDRESS``; ``None`` for a new local cluster."""
    given = [arg.split("=", 1)[1] for arg in hydra_args
             if arg.startswith("hydra.launcher.ray.init.address=")]
    address = given[-1] if given else os.environ.get("RAY_ADDRESS")
    return None if address in (None, "", "null", "None") else address


def check_ray_address(address: str, key: str = "hydra.launcher.ray.init.address") -> None:
    """Refuse a cluster address ``host:port`` where nothing listens (one try to connect, up to
    5 s), before any job starts; ``auto``, ``local`` and ``ray://`` addresses are Ray's to
    resolve."""
    if address in ("auto", "local") or "://" in address:
        return
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(key, address, "allowed: host:port of the cluster's head, auto, or "
                          "ray://host:port")
    try:
        socket.create_connection((host, int(port)), timeout=5).close()
    except OSError as error:
        raise ConfigError(key, address, f"nothing answers there ({error.strerror or error}): "
                          "start the cluster (ray start --head) or give its head's address"
                          ) from None


def launcher_overrides(launcher: str, jobs: int | None,
                       hydra_args: Sequence[str] = ()) -> list[str]:
    """The Hydra overrides that select ``launcher`` (``jobs``: parallel jobs of ``local``).

    Ray joins the cluster of :func:`ray_address` when there is one; the Ray launcher's default
    object store size, which only a new local cluster accepts, is then left out."""
    if launcher == "local":
        return ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs or -1}"]
    if launcher in ("basic", "none"):
        return []
    if launcher == "ray":
        joins = ray_address(hydra_args) is not None
        return ["hydra/launcher=ray", *(
            ["+hydra.launcher.ray.init.object_store_memory=null"] if joins else [])]
    if launcher == "slurm":
        return ["hydra/launcher=submitit_slurm"]
    raise ConfigError("launcher", launcher, f"allowed: {', '.join(LAUNCHERS)}")


WORKER = "armeta_rl.reproduce.progress.SweepWorker"


def train_job(results: Path, run: TrainRun) -> dict:
    """The sweeper's entry for ``run``: its overrides, or ``resume=`` for an interrupted run (its
    directory holds its config): it continues from its last checkpoint, or starts again from the
    beginning if it had written none, bit-identical to an uninterrupted run either way. A resume
    takes the plan's keys that change no result (:data:`~armeta_rl.cli.jobs.NO_RESULT_KEYS`:
    how often it checkpoints, its progress bar), so a run started before the plan changed them
    follows the plan's from then on."""
    from armeta_rl.cli.jobs import NO_RESULT_KEYS

    overrides = run.command(results)
    if interrupted(results, run):
        overrides = [f"resume={results / run.subdir}", *(
            o for o in overrides if o.split("=", 1)[0].lstrip("+") in NO_RESULT_KEYS)]
    return {"name": run.subdir, "overrides": [*overrides, f"hydra.sweep.subdir={run.subdir}"],
            "done": str(results / run.subdir / "eval.json")}


def eval_job(results: Path, job: EvalJob) -> dict:
    """The sweeper's entry for an ``armeta-eval`` job."""
    return {"name": job.out, "overrides": [*job.command(results),
                                           f"hydra.sweep.subdir={job.learner.subdir}"],
            "done": str(results / job.out)}


def launch(entry: Callable[[list[str]], int], jobs: Sequence[dict], results: Path,
           label: str, finished_before: int, hydra_args: Sequence[str],
           local_workers: bool = False) -> int:
    """Run ``jobs`` as one multirun of ``entry`` (``armeta_rl.cli.train`` or ``evaluate``, which
    take the command line's arguments) and return its exit code (0 when every job finished).

    The jobs file goes to ``results/.sweeps/<label>.yaml`` (kept: it records what was launched).
    With ``local_workers`` (joblib processes of this machine) each job's worker also runs
    :class:`~armeta_rl.reproduce.progress.SweepWorker`: it stops its runs when this process
    asks or dies.
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
            *([f"+hydra.callbacks.worker._target_={WORKER}",
               f"+hydra.callbacks.worker.sweep_pid={os.getpid()}"] if local_workers else []),
            *hydra_args]
    return entry(argv)
