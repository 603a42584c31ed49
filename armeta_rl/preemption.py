"""Stopping a run cleanly on a signal (docs/configuration.md, "Preemption").

A cluster asks a job to stop with a signal before it kills it: Slurm sends ``SIGTERM`` (or the
signal of ``--signal``) and waits ``KillWait`` seconds before ``SIGKILL``; Kubernetes sends
``SIGTERM`` and waits the pod's grace period; submitit's timeout signal is ``SIGUSR2``. While
:func:`listening`, such a signal (``trainer.stop_signals``) and ``SIGINT`` (Ctrl-C) only set the
process's :class:`StopRequest`; the game loop checks it after every iteration, writes a
checkpoint and returns, and the command prints one line naming the checkpoint and the resume
command and exits with :data:`EXIT_PREEMPTED` (:data:`EXIT_INTERRUPTED` for ``SIGINT``). A
signal that arrives while a checkpoint is written lets the write finish. A second ``SIGINT``
stops at once (``KeyboardInterrupt``), keeping the last checkpoint.

The request belongs to the process, as signals do: a process that was asked to stop starts no
further run (the later jobs of a joblib worker of a sweep stop before training).

Work that keeps nothing until it ends (an evaluation, whose report is written whole at the end)
has nothing to save: :func:`abandoning` stops it at once on such a signal.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from types import FrameType

from armeta_rl.errors import RunNotStarted, RunStopped

STOP_SIGNALS = ("SIGTERM", "SIGUSR1", "SIGUSR2", "SIGHUP", "SIGXCPU")
"""The signals ``trainer.stop_signals`` may name (``SIGINT`` is always handled)."""
EXIT_PREEMPTED = 75
"""The exit code of a run stopped by one of ``trainer.stop_signals``: ``EX_TEMPFAIL`` of
``sysexits.h``, a temporary failure, so a requeue runs the same command again."""
EXIT_INTERRUPTED = 130
"""The exit code of a run stopped by ``SIGINT``, as a shell reports Ctrl-C (128 + 2)."""


class StopRequest:
    """Whether the process was asked to stop, and by which signal (the first one received)."""

    def __init__(self) -> None:
        self.signal: signal.Signals | None = None

    @property
    def requested(self) -> bool:
        return self.signal is not None

    @property
    def name(self) -> str:
        """The signal's name (``SIGTERM``), or ``a stop request`` for one made without a signal."""
        return self.signal.name if self.signal is not None else "a stop request"

    @property
    def exit_code(self) -> int:
        return EXIT_INTERRUPTED if self.signal == signal.SIGINT else EXIT_PREEMPTED

    def request(self, signum: int) -> None:
        """Ask the process to stop because of ``signum`` (the first request's signal is kept)."""
        if self.signal is None:
            self.signal = signal.Signals(signum)


PROCESS = StopRequest()
"""This process's stop request, set by the handlers :func:`listening` installs."""


@contextmanager
def listening(names: Iterable[str], request: StopRequest = PROCESS,
              forward_to_children: bool = False) -> Iterator[StopRequest]:
    """Within the block, the signals ``names`` (from :data:`STOP_SIGNALS`) and ``SIGINT`` set
    ``request`` instead of ending the process; the handlers in place before are restored after.

    With ``forward_to_children`` the first signal is also sent on, as ``SIGTERM``, to the
    ``multiprocessing`` children (the joblib workers of ``armeta-reproduce launcher=local``),
    whose runs stop alike. Outside the main thread (where Python cannot handle signals) nothing
    is installed and the block runs as it would without.
    """

    def handle(signum: int, frame: FrameType | None) -> None:
        first = not request.requested
        if signum == signal.SIGINT and request.signal == signal.SIGINT:
            raise KeyboardInterrupt  # Ctrl-C twice: stop now
        request.request(signum)
        if first and forward_to_children:
            for child in multiprocessing.active_children():
                if child.pid is not None:
                    os.kill(child.pid, signal.SIGTERM)

    with _handled(names, handle):
        yield request


def refuse_if_asked(again: str, request: StopRequest = PROCESS) -> None:
    """Refuse to start work in a process asked to stop (a later job of a sweep worker that
    received ``SIGTERM``): :class:`~armeta_rl.errors.RunNotStarted`, saying that ``again`` does
    it, with the request's exit code."""
    if request.requested:
        raise RunNotStarted(f"not started: this process received {request.name}; {again}",
                            request.exit_code)


@contextmanager
def abandoning(what: str, again: str, names: Iterable[str] = STOP_SIGNALS,
               request: StopRequest = PROCESS) -> Iterator[None]:
    """Within the block, ``what`` (work that keeps nothing until it ends) stops at once on one
    of the signals ``names`` or ``SIGINT``: the signal becomes ``request`` and
    :class:`~armeta_rl.errors.RunStopped` is raised where the work is, with the request's exit
    code and a line saying that nothing was written and that ``again`` does it. A process asked
    to stop before the block does none of it (:func:`refuse_if_asked`). The handlers in place
    before are restored after; outside the main thread none is installed.
    """
    refuse_if_asked(again, request)

    def handle(signum: int, frame: FrameType | None) -> None:
        request.request(signum)
        raise RunStopped(f"{what} stopped by {signal.Signals(signum).name}: nothing written; "
                         f"{again}", request.exit_code)

    with _handled(names, handle):
        yield


@contextmanager
def _handled(names: Iterable[str], handle: Callable[[int, FrameType | None], None]
             ) -> Iterator[None]:
    """Within the block, ``SIGINT`` and the signals ``names`` call ``handle``; the handlers in
    place before are restored after. Outside the main thread (where Python cannot handle
    signals) nothing is installed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    wanted = {signal.SIGINT, *(signal.Signals[name] for name in names)}
    previous = {sig: signal.signal(sig, handle) for sig in wanted}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
