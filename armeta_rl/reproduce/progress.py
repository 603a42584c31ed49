"""Progress of a sweep: a Hydra callback that prints, as each job starts and ends, which run it is,
how many of the experiment's jobs are finished and left, and the time since the sweep started.

It runs where the job runs (a joblib worker, a Ray worker, a Slurm node) and counts finished jobs
from the files they write (each job's ``done`` file in the sweeper's jobs file; a job's name is
its entry at ``hydra.job.num``), so it holds no state of its own and counts correctly whichever
worker prints.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path
from types import FrameType
from typing import Any

from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from armeta_rl.errors import JobFailed
from armeta_rl.preemption import EXIT_INTERRUPTED, EXIT_PREEMPTED, PROCESS
from armeta_rl.reproduce import read_jobs


def format_elapsed(seconds: float) -> str:
    """``h:mm:ss``."""
    seconds = int(seconds)
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class Progress(Callback):
    """Print ``[<label>] <event> <job>: <done>/<total> finished, <left> left, <elapsed>``
    (events: ``start``, then :func:`job_event`'s).

    Args:
        jobs_file: the sweeper's jobs file (each job's ``done`` path).
        label: what the sweep is, e.g. ``table1 train``.
        started: the sweep's start (seconds since the epoch).
        finished_before: jobs of the experiment finished before this sweep (skipped).
    """

    def __init__(self, jobs_file: str, label: str, started: float, finished_before: int) -> None:
        self.jobs_file = jobs_file
        self.label = label
        self.started = started
        self.finished_before = finished_before

    def line(self, event: str, config: DictConfig) -> str:
        """The progress line for ``event`` of the job whose config is ``config``."""
        jobs = read_jobs(self.jobs_file)
        done = self.finished_before + sum(Path(job["done"]).is_file() for job in jobs)
        total = self.finished_before + len(jobs)
        elapsed = format_elapsed(time.time() - self.started)
        name = jobs[config.hydra.job.num]["name"]
        return (f"[{self.label}] {event} {name}: {done}/{total} finished, "
                f"{total - done} left, elapsed {elapsed}")

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        if not PROCESS.requested:  # a job of a worker asked to stop does not start
            print(self.line("start", config), flush=True)

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        event = job_event(job_return)
        if event is not None:
            print(self.line(event, config), flush=True)


def job_event(job_return: JobReturn) -> str | None:
    """How a job ended: ``done``, ``stopped`` (a stop signal: it checkpointed, the same command
    continues it), ``FAILED``, or ``None`` for a job that never started because its worker had
    been asked to stop. Hydra keeps a failed job's exception as its return value."""
    if job_return.status == JobStatus.COMPLETED:
        return "done"
    error = job_return._return_value
    if isinstance(error, JobFailed) and not error.started:
        return None
    if getattr(error, "code", None) in (EXIT_PREEMPTED, EXIT_INTERRUPTED):
        return "stopped"
    return "FAILED"


class SweepWorker(Callback):
    """Make a joblib worker of a sweep stop its runs with the sweep (``armeta-reproduce
    launcher=local``), and end once the sweep's process ``sweep_pid`` is gone.

    As a job starts in the worker, the worker's ``SIGTERM`` and ``SIGUSR1`` set its stop request
    for good (:data:`armeta_rl.preemption.PROCESS`): the run in flight checkpoints and stops
    (while it trains, :func:`~armeta_rl.preemption.listening` handles them alike), an evaluation
    in flight stops at once (:func:`~armeta_rl.preemption.abandoning`), and the worker's later
    jobs stop before starting. The sweep's process forwards its own stop signals
    to its workers. A thread watches the sweep's process: once it is gone (``SIGKILL``, say),
    the worker sends itself ``SIGTERM``, and exits as soon as no run of it is in flight.
    """

    def __init__(self, sweep_pid: int, every: float = 1.0) -> None:
        self.sweep_pid, self.every = int(sweep_pid), every

    def orphaned(self) -> bool:
        return os.getppid() != self.sweep_pid

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        if os.getpid() == self.sweep_pid or threading.current_thread() is not (
                threading.main_thread()):
            return
        for sig in (signal.SIGTERM, signal.SIGUSR1):
            signal.signal(sig, self._stop)
        if not any(thread.name == "sweep-watch" for thread in threading.enumerate()):
            threading.Thread(target=self._watch, name="sweep-watch", daemon=True).start()

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        if os.getpid() != self.sweep_pid and self.orphaned():
            os._exit(EXIT_PREEMPTED)  # the run checkpointed; nobody reads its result

    def _stop(self, signum: int, frame: FrameType | None) -> None:
        """Between jobs: a worker whose sweep is gone has nothing to finish; otherwise no later
        job of it starts."""
        PROCESS.request(signum)
        if self.orphaned():
            os._exit(EXIT_PREEMPTED)

    def _watch(self) -> None:
        while not self.orphaned():
            time.sleep(self.every)
        os.kill(os.getpid(), signal.SIGTERM)
