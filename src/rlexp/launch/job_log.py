"""The job's log file in its run dir (Hydra's ``<run_dir>/train.log``) is written only once the run
owns that dir.

Hydra opens the job's log file before rlexp's task function runs, so a launch that is then refused
(the dir is in use by another run, or holds another experiment) would append its own lines, the
refusal included, to the log of the run that owns the dir. :class:`HoldJobLog` (a Hydra callback,
``hydra.callbacks.rlexp_job_log`` in conf/config.yaml) takes the job's file handlers off the root
logger when the job starts and keeps its records in memory; ``release`` writes them and puts the
handlers back once the run holds the dir's lock and its checks passed (``rlexp.app``); ``drop``
closes the file untouched when the launch stops before that (its one line still goes to the
console).
"""

from __future__ import annotations

import logging
from typing import Any

from hydra.experimental.callback import Callback

#: Records kept while the log is held (a start-up logs a few dozen; more are counted, not kept).
MAX_HELD = 10_000


class _Held(logging.Handler):
    """Keeps the records meant for one file handler until the run owns its dir."""

    def __init__(self, target: logging.FileHandler) -> None:
        super().__init__(target.level)
        self.target = target
        self.records: list[logging.LogRecord] = []
        self.dropped = 0

    def emit(self, record: logging.LogRecord) -> None:
        if len(self.records) < MAX_HELD:
            self.records.append(record)
        else:
            self.dropped += 1


_HELD: list[_Held] = []


def hold() -> None:
    """Hold the records of the root logger's file handlers (the job's log files)."""
    release()  # an earlier job of this process that never got that far
    root = logging.getLogger()
    for handler in list(root.handlers):
        if isinstance(handler, logging.FileHandler):
            held = _Held(handler)
            root.removeHandler(handler)
            root.addHandler(held)
            _HELD.append(held)


def release() -> None:
    """The run owns its dir: write the held records to its log file and log there from now on."""
    root = logging.getLogger()
    while _HELD:
        held = _HELD.pop()
        root.removeHandler(held)
        root.addHandler(held.target)
        for record in held.records:
            held.target.handle(record)
        if held.dropped:
            note = f"({held.dropped} more start-up log records were not kept)"
            held.target.handle(
                logging.LogRecord(__name__, logging.WARNING, "", 0, note, None, None)
            )


def drop() -> None:
    """The launch is refused: its log file is closed unwritten (it belongs to another run)."""
    root = logging.getLogger()
    while _HELD:
        held = _HELD.pop()
        root.removeHandler(held)
        held.target.close()


def held() -> bool:
    """Whether the job's log file is still held (the run has not yet shown the dir is its own)."""
    return bool(_HELD)


class HoldJobLog(Callback):
    """``hydra.callbacks.rlexp_job_log``: hold the job's log file from the job's start (before the
    other callbacks log into it) until the run owns its dir; what is still held at the job's end
    (a job that returned early, e.g. a finished one skipped) is written then."""

    def on_job_start(self, config: Any = None, **kwargs: Any) -> None:
        hold()

    def on_job_end(self, config: Any = None, job_return: Any = None, **kwargs: Any) -> None:
        release()
