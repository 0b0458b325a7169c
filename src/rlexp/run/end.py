"""How a failed run keeps what it can: the update before the failure as a checkpoint, the traceback
in ``error.log``, ``failed`` in ``status.json`` (``rlexp.run.lifecycle.RunLifecycle.run``)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from rlexp.config.rules import first_line
from rlexp.run.rundir import write_status

log = logging.getLogger(__name__)


def save_at_safe_point(trainer: Any) -> bool:
    """After a failure between an update and the end of its iteration (eval, an event, logging),
    the policy and optimiser are consistent: save them so the work of that update is not lost."""
    if not trainer.safe_point or not trainer.dist.is_main:
        return False
    try:
        trainer.save_checkpoint()
        return True
    except Exception as exc:
        log.error("could not save a checkpoint after the failure: %s", first_line(exc))
        return False


def write_traceback(run_dir: Path) -> Path:
    """The full traceback of the exception being handled, into ``<run_dir>/error.log``."""
    import traceback

    path = run_dir / "error.log"
    try:
        with open(path, "a") as f:
            f.write(traceback.format_exc())
    except OSError:
        pass
    return path


def try_write_status(run_dir: Path, trainer: Any, reason: str) -> None:
    try:
        write_status(run_dir, "failed", trainer.global_step, trainer.last_eval, reason=reason)
    except OSError as exc:
        log.error("could not write %s: %s", run_dir / "status.json", exc)
