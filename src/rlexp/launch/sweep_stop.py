"""Ctrl-C, SIGTERM or SIGHUP on a local parallel sweep (``hydra/launcher=local``): the jobs stop
as a single run does.

Why this is needed: Ctrl-C in a terminal reaches every process of its process group, the sweep's
process and its job processes alike (``launch/job_pool.py``; joblib's loky workers before). The workers' runs record the request and go on to the
end of their iteration, but the sweep's process, left with Python's default, raised
``KeyboardInterrupt`` inside joblib, and joblib then killed its workers (SIGKILL) mid-iteration: no
stop checkpoint, ``status.json`` left ``running``. A SIGTERM to the sweep's process alone
(``timeout``, SLURM, ``kill``) killed it and left the workers running on, orphaned.

What :class:`ParentStop` does while the job pool runs a batch:

- the sweep's process never raises on a stop signal: the first is recorded, logged, and sent on
  to each worker (SIGTERM in place of a SIGINT: a worker in the terminal's group has the Ctrl-C
  already, and a second SIGINT would mean "stop now, without a checkpoint"); a worker's run takes
  the first stop it gets and ignores the rest, so each running job finishes its iteration, saves
  and writes ``interrupted``;
- the stop signals stay blocked in the sweep's threads and are taken by a thread of its own
  (``sigtimedwait``): a worker started meanwhile inherits the blocked mask, so a signal during its
  start-up waits until its initializer (``signals.become_sweep_worker``) can record it;
- no further job starts after a stop, and the pool collects every running job's return; then
  the sweep exits 128 + N without its summary (:func:`exit_stopped`), as a single run does.
  Running the same command again resumes the interrupted jobs.

A second Ctrl-C in the terminal reaches the workers directly: their runs stop at once, without a
checkpoint (docs/faults.md). The sweep's process does not forward a second signal.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterable
from typing import Any

from rlexp.run.rundir import EXIT_SIGNAL_BASE
from rlexp.runtime.signals import STOP_SIGNALS, SWEEP_STOPPING_ENV

log = logging.getLogger(__name__)


#: How long the waiting thread sleeps in ``sigtimedwait`` before it looks whether the batch ended.
POLL_S = 0.2


class ParentStop:
    """``with ParentStop(pids) as stop:`` the sweep's process while its workers run jobs: a stop
    signal is recorded (``stop.signum``) and sent on to ``pids()``, never raised."""

    def __init__(self, pids: Callable[[], Iterable[int]]) -> None:
        self.pids = pids
        self.signum: int | None = None
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self._signals: tuple[int, ...] = ()
        self._previous: dict[int, Any] = {}
        self._old_mask: set[int] | None = None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum is not None else ""

    def received(self, signum: int) -> None:
        """The first stop: record, log, tell the workers; a later one only logs."""
        with self._lock:
            first = self.signum is None
            if first:
                self.signum = signum
                os.environ[SWEEP_STOPPING_ENV] = signal.Signals(signum).name
        name = signal.Signals(signum).name
        if not first:
            log.warning(
                "%s: the sweep is already stopping (a Ctrl-C in the terminal reaches the jobs "
                "too: a second one stops them at once, without a checkpoint)",
                name,
            )
            return
        log.warning(
            "%s: stopping the sweep: running jobs finish their iteration and save a checkpoint; "
            "no new job starts",
            name,
        )
        forward = signal.SIGTERM if signum == signal.SIGINT else signum
        for pid in self.pids():
            try:
                os.kill(pid, forward)
            except (ProcessLookupError, PermissionError):
                pass  # ended meanwhile

    def _handle(self, signum: int, frame: Any) -> None:
        self.received(signum)

    def _wait(self) -> None:
        while not self._done.is_set():
            info = signal.sigtimedwait(self._signals, POLL_S)
            if info is not None:
                self.received(info.si_signo)

    def __enter__(self) -> ParentStop:
        if threading.current_thread() is not threading.main_thread():
            return self  # signal handlers belong to the main thread: leave them as they are
        # A signal the parent set to be ignored (nohup, a background job) stays ignored.
        self._signals = tuple(s for s in STOP_SIGNALS if signal.getsignal(s) is not signal.SIG_IGN)
        # Handlers first: a thread that does not block the signals (one torch or MuJoCo started
        # before) may be the one that receives it.
        self._previous = {s: signal.signal(s, self._handle) for s in self._signals}
        if hasattr(signal, "sigtimedwait") and self._signals:
            self._old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, self._signals)
            self._thread = threading.Thread(target=self._wait, name="rlexp-sweep-stop", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._old_mask is not None:  # first: one pending now goes to _handle, still installed
            signal.pthread_sigmask(signal.SIG_SETMASK, self._old_mask)
            self._old_mask = None
        if self._thread is not None:
            self._done.set()
            self._thread.join()
            self._thread = None
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}


def exit_stopped(sweep_dir: str, stop: ParentStop) -> None:
    """The sweep was stopped by a signal: one line, exit 128 + N (its summary is not printed)."""
    log.error(
        "sweep %s stopped by %s: its running jobs saved a checkpoint and say interrupted; run the "
        "same command again to resume them",
        sweep_dir,
        stop.name,
    )
    sys.exit(EXIT_SIGNAL_BASE + stop.signum)
