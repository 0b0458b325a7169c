"""SIGINT, SIGTERM and SIGHUP while no run trains in this process: at start-up, and once a run's final
``status.json`` is written (its shut-down, and the gap before a sweep's next job).

While a run trains, ``runtime/signals.py`` turns a stop signal into a checkpoint at the iteration's
end. Outside that window the entry point's handlers (``install``) decide:

* start-up (before the run's handlers are in place): Ctrl-C raises ``KeyboardInterrupt``, which the
  entry point (``runtime/entry.py``) turns into one line and exit 130; SIGTERM and SIGHUP end the
  process as their default action does (nothing has been written yet).
* after the final status (``run_ended``): the run's work is done and its status says how it ended,
  so a stop signal must not change either. It is recorded and logged; a single run exits with the
  code its status implies (0 for ``finished``); a sweep stops before its next job starts
  (``job_started``: one line, exit 128 + N), the finished jobs stay finished. Should the shut-down
  (closing loggers, W&B's upload) hang, the process leaves :data:`SHUTDOWN_GRACE_S` after the
  signal with that same code.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from typing import Any

from rlexp.runtime.entry import SignalInterrupt, interrupted, note_sigint

log = logging.getLogger(__name__)

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
EXIT_SIGNAL_BASE = 128  # rlexp.run.rundir.EXIT_SIGNAL_BASE (not imported: this module stays light)

#: Seconds a stop signal after the final status waits for the shut-down before the process leaves.
SHUTDOWN_GRACE_S = 30.0

#: ``final``: a run's final status is written; ``pending``: a stop signal that came after it;
#: ``code``: the exit code that status implies (None: unknown); ``sweep``: this process runs a sweep.
_STATE: dict[str, Any] = {"final": False, "pending": None, "code": 0, "sweep": False}


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def install(sweep: bool = False) -> None:
    """The entry point's stop-signal handlers (a signal the parent ignores stays ignored). The run's
    own handlers (``stop_on_signals``) go on top of these and put them back when the run ends."""
    _STATE.update(final=False, pending=None, code=0, sweep=sweep)
    note_sigint(False)
    _set_handlers()


def _set_handlers() -> None:
    if not _main_thread():
        return
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, _handle)


def _handle(signum: int, frame: Any) -> None:
    if not _STATE["final"]:  # start-up: nothing to save yet
        if signum == signal.SIGINT:
            note_sigint()  # whatever the code it lands in makes of it (entry.interrupted)
            raise SignalInterrupt
        signal.signal(signum, signal.SIG_DFL)  # SIGTERM / SIGHUP: their default action, as before
        os.kill(os.getpid(), signum)
        return
    worker = _sweep_worker()
    if worker is not None:  # a local sweep's joblib worker: it starts no further job
        worker.note(signum)
        return
    if _STATE["pending"] is None:
        _STATE["pending"] = signum
        log.warning(
            "%s received after the run ended (its status.json says how): finishing the shut-down "
            "(at most %g s)%s",
            signal.Signals(signum).name,
            SHUTDOWN_GRACE_S,
            "; the sweep starts no further job" if _STATE["sweep"] else "",
        )
        timer = threading.Timer(SHUTDOWN_GRACE_S, _leave, args=(signum,))
        timer.daemon = True
        timer.start()


def _sweep_worker() -> Any:
    """This process's ``SweepWorker`` when it is a joblib worker of a local sweep, else None."""
    from rlexp.runtime import signals

    return getattr(signals, "sweep_worker", lambda: None)()


def _leave(signum: int) -> None:
    """The shut-down outlived its grace: leave with the code the run's status implies."""
    code = _STATE["code"]
    if _STATE["sweep"] or code is None:
        code = EXIT_SIGNAL_BASE + signum
    sys.stderr.write(f"the shut-down did not end {SHUTDOWN_GRACE_S:g} s after the signal: exit\n")
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def run_ended() -> None:
    """Call where the run's final status is written (in the ``finally`` that follows it): from now
    on a stop signal is recorded, not acted on; the exit code is that of the exception in flight
    (``RunEnded.exit_code``; 0 when the run finished). The run's own handlers are replaced at once
    (they would ask a finished run to checkpoint, and a stuck close would exit 128 + N while the
    status says ``finished``); ``stop_on_signals`` puts back the entry point's, these same ones."""
    exc = sys.exc_info()[1]
    _STATE["final"] = True
    _STATE["code"] = 0 if exc is None else getattr(exc, "exit_code", None)
    _set_handlers()


def job_started(label: str) -> None:
    """A sweep job (or a run) starts in this process: a stop signal that came after the previous
    job's end stops the sweep here, before this job writes anything (one line, exit 128 + N)."""
    signum = _STATE["pending"]
    _STATE.update(final=False, pending=None)
    if signum is None:
        return
    name = signal.Signals(signum).name
    log.error(
        "%s received after the previous job ended: the sweep stops before %s (not started; "
        "the same command runs it and skips the finished jobs)",
        name,
        label,
    )
    sys.exit(EXIT_SIGNAL_BASE + signum)


def reraise_if_interrupted(exc: BaseException) -> None:
    """Raise ``KeyboardInterrupt`` if ``exc`` came out of one (``entry.interrupted``): a Ctrl-C at
    start-up that landed inside a library's ``finally`` (OmegaConf's, seen at 0.5 s) surfaces as
    that library's error, e.g. an ``AttributeError`` of a half-built object wrapped in a config
    error, and one inside MuJoCo's C-extension import as ``ImportError: initialization failed``
    (seen at 2.0 s); it must still end as a Ctrl-C does (one line, exit 130), not as a config error
    or a traceback."""
    if interrupted(exc):
        raise KeyboardInterrupt from None
