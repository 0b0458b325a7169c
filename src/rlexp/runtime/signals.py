"""SIGINT, SIGTERM and SIGHUP ask the run to stop at a safe point; they never cut an update in half.

``docker stop``, ``timeout``, systemd, ``kill`` and SLURM at the time limit send SIGTERM; a closed
terminal or SSH session sends SIGHUP; Ctrl-C sends SIGINT. Each only records the request: the
Trainer finishes the current iteration (collect, update, log, eval, save), writes a checkpoint and
stops, so a resume continues bit-exactly. A second Ctrl-C stops at once without a checkpoint (the
last one on disk stays good). SLURM's preemption signal (USR2) goes through ``launch/slurm.py``.

A local sweep's joblib workers (``hydra/launcher=local``) are :class:`SweepWorker` processes: a stop
signal that reaches one between jobs is remembered, no later job starts there, and the sweep's
process (``launch/sweep_stop.py``) collects every job before it exits 128 + N.

rlexp's child processes (the eval worker, the overlap child, the ``gymnasium_async`` workers, a local
sweep's jobs) start with the stop signals :func:`blocked` and end with their parent
(:func:`die_with_parent`).
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, Protocol

from rlexp.runtime.entry import SignalInterrupt

log = logging.getLogger(__name__)

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Stoppable(Protocol):
    def request_stop(self, reason: str) -> None: ...


class StopSignals:
    """What arrived, and who to tell: the Trainer once it exists (a signal during the build is
    remembered and handed over)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.target: Stoppable | None = None
        #: called with the signal at the first request (rlexp.run.stalls.StopWatchdog.arm)
        self.watchers: list[Callable[[int], None]] = []

    @property
    def requested(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum is not None else ""

    def attach(self, target: Stoppable) -> None:
        """Forward requests to ``target`` (e.g. the Trainer), including one that came before."""
        self.target = target
        if self.signum is not None:
            target.request_stop(self.reason())

    def reason(self) -> str:
        return f"{self.name} received"

    def _handle(self, signum: int, frame: Any) -> None:
        if _WORKER is not None:
            _WORKER.note(signum)  # no later job of the sweep starts in this process
        if self.signum is not None and signum == signal.SIGINT:
            raise SignalInterrupt  # a second Ctrl-C: stop now, no checkpoint
        if self.signum is not None:
            return
        self.signum = signum
        for watch in self.watchers:
            watch(signum)
        log.warning(
            "%s: stopping after the current iteration with a checkpoint%s",
            self.name,
            " (press Ctrl-C again to stop now without one)" if signum == signal.SIGINT else "",
        )
        if self.target is not None:
            self.target.request_stop(self.reason())


@contextmanager
def stop_on_signals() -> Iterator[StopSignals]:
    """Install the stop handlers for the duration of a run (main thread only; restored after)."""
    stops = StopSignals()
    if _WORKER is not None and _WORKER.signum is not None:
        stops.signum = _WORKER.signum  # came while this sweep job was starting: stop at once
    if threading.current_thread() is not threading.main_thread():
        yield stops
        return
    # A signal the parent set to be ignored (nohup, a background job) stays ignored.
    previous = {
        sig: signal.getsignal(sig)
        for sig in STOP_SIGNALS
        if signal.getsignal(sig) is not signal.SIG_IGN
    }
    for sig in previous:
        signal.signal(sig, stops._handle)
    try:
        yield stops
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


#: Set by the sweep's process once it got a stop signal: a joblib worker started after that (it
#: inherits the environment) starts no job.
SWEEP_STOPPING_ENV = "RLEXP_SWEEP_STOPPING"


class SweepWorker:
    """This process runs jobs of a local sweep (a joblib worker). The first stop signal it gets,
    in a job or between two, is kept: the job's run stops at its safe point, and the jobs that
    joblib hands this process afterwards do not start (``rlexp.app._task``)."""

    def __init__(self, signum: int | None = None) -> None:
        self.signum = signum

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum is not None else ""

    def note(self, signum: int) -> None:
        if self.signum is None:
            self.signum = signum


_WORKER: SweepWorker | None = None


def sweep_worker() -> SweepWorker | None:
    """This process's :class:`SweepWorker`, or None outside a local sweep's worker processes."""
    return _WORKER


def become_sweep_worker() -> None:
    """The joblib workers' initializer (``launch/sweep_stop.py``): record stop signals while no
    job runs here (a job's run installs its own handlers on top, ``stop_on_signals``), then take
    the stop signals that the sweep's process kept blocked while it started this one: a Ctrl-C
    during the worker's start-up is held until now, and then only recorded."""
    global _WORKER
    if _WORKER is None:
        name = os.environ.get(SWEEP_STOPPING_ENV, "")
        _WORKER = SweepWorker(getattr(signal, name) if name.startswith("SIG") else None)
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is not signal.SIG_IGN:  # nohup's ignored SIGHUP stays ignored
            signal.signal(sig, _worker_handle)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


@contextmanager
def blocked(signals: tuple[signal.Signals, ...] | set[signal.Signals]) -> Iterator[None]:
    """Meanwhile ``signals`` are blocked in this thread: a child started now inherits them blocked
    (it unblocks them once its handlers are in place); one that arrives meanwhile is delivered here
    afterwards, not lost. A no-op where there is no ``pthread_sigmask``."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def die_with_parent(parent: int, sig: signal.Signals = signal.SIGKILL) -> None:
    """In a child process: ``sig`` to this process when ``parent`` (its parent's PID) ends, even
    where it hangs and never reads the closed pipe (Linux's ``PR_SET_PDEATHSIG``; elsewhere only the
    pipe's end stops it). A parent that ended before the call (or, elsewhere, before this process
    started) sends nothing: this process then gets ``sig`` at once, as if it had come."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(sig))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError, TypeError):  # not Linux (TypeError: Windows's CDLL(None))
        pass
    if os.getppid() != parent:
        os.kill(os.getpid(), sig)


def _worker_handle(signum: int, frame: Any) -> None:
    """Between two jobs of a sweep worker: remember the stop; no job of this sweep starts here."""
    if _WORKER is None:
        return
    if _WORKER.signum is None:
        log.warning("%s: the sweep is stopping; no new job starts", signal.Signals(signum).name)
    _WORKER.note(signum)
