"""An event of this project: after every evaluation, one line per round in a CSV in the run dir."""

from __future__ import annotations

import csv

from rlexp.config.native_task import FileName
from rlexp.events import EventContext

EVAL_HISTORY_PARAMS = {"file": FileName()}

COLUMNS = ("step", "eval/episode_return", "eval/success_rate", "eval/episode_length")


def eval_history(ctx: EventContext, file: str = "eval_history.csv") -> None:
    """Append the step and the round's eval metrics to ``<run_dir>/<file>`` (mode trigger,
    signal eval_end): the learning curve in a file a spreadsheet opens."""
    if ctx.run_dir is None:
        return
    path = ctx.run_dir / file
    new = not path.exists()
    with open(path, "a", newline="") as f:
        writer = csv.writer(f)
        if new:
            writer.writerow(COLUMNS)
        writer.writerow([ctx.global_step, *(ctx.metrics.get(k, "") for k in COLUMNS[1:])])
