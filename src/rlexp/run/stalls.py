"""A run that stops making progress: what its heartbeat records, and the stop that cannot wait.

The heartbeat (``rlexp.run.rundir.Heartbeat``) is written by a thread, which proves the process lives,
not that it trains: ``progress`` gives it the step and the run's ``trainer.stall_timeout_s``, so that
``rlexp runs`` shows ``stalled`` once the step has not moved for that long (docs/runs.md).

SIGINT / SIGTERM / SIGHUP only ask the loop to stop at its next safe point (``rlexp.runtime.signals``).
A loop stuck in user code (an env whose ``step`` never returns) never gets there: ``StopWatchdog``
ends the process ``trainer.stop_grace_s`` after the signal anyway, with ``status.json`` saying
``interrupted``, that no checkpoint could be taken at the safe point, and which checkpoint is the
resume point, and the exit code 128 + N, as a stop at the safe point would.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from rlexp.run.rundir import EXIT_SIGNAL_BASE, write_status

log = logging.getLogger(__name__)


def progress(trainer: Any, total: int) -> dict[str, Any]:
    """What the heartbeat records besides who and when (read from the heartbeat's thread)."""
    cfg = trainer.config_dict
    return {
        "task": cfg["env"]["name"],  # with total: what `rlexp runs` shows without the config.yaml
        "algorithm": cfg["algorithm"]["name"],
        "global_step": trainer.global_step,
        "total": total,
        "best_metric": trainer.cfg.best_metric,
        "best": trainer.best_metric,  # -inf until the first eval: written as null
        "last_eval": dict(trainer.last_eval),
    }


class StopWatchdog:
    """Arms on the first stop request; if the process has not ended ``grace_s`` later, records the
    run as interrupted (rank 0) and exits with 128 + the signal."""

    def __init__(self, trainer: Any, run_dir: Path, resumed_from: Any, grace_s: float) -> None:
        self.trainer = trainer
        self.run_dir = Path(run_dir)
        self.resumed_from = resumed_from  # the checkpoint this attempt started from, if any
        self.grace_s = grace_s
        self.ended = False  # True once status.json says how the run ended: only exit then
        self._thread: threading.Thread | None = None
        self._cancel = threading.Event()

    def arm(self, signum: int) -> None:
        """Start the countdown (from the signal handler: returns at once; once per run)."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(
            target=self._wait, args=(signum,), name="rlexp-stop-watchdog", daemon=True
        )
        self._thread.start()

    def disarm(self) -> None:
        """The run has ended and let go of everything: no exit from here (a sweep's process goes
        on with its other jobs)."""
        self._cancel.set()

    def _wait(self, signum: int) -> None:
        if not self._cancel.wait(self.grace_s):
            self.expire(signum)

    def reason(self, signum: int) -> str:
        """What ``status.json`` says: the signal, that the loop did not reach its safe point, and the
        checkpoint a resume continues from."""
        name = signal.Signals(signum).name
        path = self.trainer.last_checkpoint or self.resumed_from
        point = f"the resume point is {path}" if path else "no checkpoint was written yet"
        return (
            f"{name} received at step {self.trainer.global_step}: the loop did not reach its safe "
            f"point within trainer.stop_grace_s={self.grace_s:g} s (stuck in an env step or other "
            f"user code?), so no checkpoint was possible at the safe point; {point}"
        )

    def expire(self, signum: int) -> None:
        """Record the run as interrupted (unless it already says how it ended) and leave now."""
        code = EXIT_SIGNAL_BASE + signum
        if not self.ended:
            reason = self.reason(signum)
            log.error("interrupted: %s", reason)
            try:
                write_status(self.run_dir, "interrupted", self.trainer.global_step,
                             self.trainer.last_eval, reason=reason)  # fmt: skip
            except OSError as exc:
                log.error("could not write %s: %s", self.run_dir / "status.json", exc)
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)  # the main thread is stuck: no teardown can be waited for
