"""SIGINT, SIGTERM and SIGHUP ask the run to stop at a safe point; they never cut an update in half.

``docker stop``, ``timeout``, systemd, ``kill`` and SLURM at the time limit send SIGTERM; a closed
terminal or SSH session sends SIGHUP; Ctrl-C sends SIGINT. Each only records the request: the
Trainer finishes the current iteration (collect, update, log, eval, save), writes a checkpoint and
stops, so a resume continues bit-exactly. A second Ctrl-C stops at once without a checkpoint (the
last one on disk stays good). SLURM's preemption signal (USR2) goes through ``launch/slurm.py``.
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, Protocol

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
        #: called with the signal at the first request (rlexp.stalls.StopWatchdog.arm)
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
        if self.signum is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt  # a second Ctrl-C: stop now, no checkpoint
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
