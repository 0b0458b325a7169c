"""A live console progress line (rich): steps, steps/s and the recent episode return."""

from __future__ import annotations

import sys

from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.progress import Progress as RichProgress


class Progress:
    """Shown only on a terminal (and when enabled); otherwise a no-op, the log lines carry progress."""

    def __init__(self, total: int, enabled: bool = True, start: int = 0) -> None:
        self.enabled = enabled and sys.stderr.isatty()
        self._bar: RichProgress | None = None
        self._task = None
        self.total = total
        self.start = start

    def __enter__(self) -> Progress:
        if self.enabled:
            self._bar = RichProgress(
                TextColumn("[bold]train"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("steps  {task.fields[sps]:>6} sps  return {task.fields[ret]}"),
                TimeElapsedColumn(),
                TimeRemainingColumn(),
                transient=False,
            )
            self._bar.__enter__()
            self._task = self._bar.add_task(
                "train", total=self.total, completed=self.start, sps="-", ret="-"
            )
        return self

    def update(self, step: int, sps: float, ret: float | None) -> None:
        if self._bar is not None:
            ret_s = "-" if ret is None else f"{ret:.2f}"
            self._bar.update(
                self._task, completed=min(step, self.total), sps=f"{sps:.0f}", ret=ret_s
            )

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.__exit__(*exc)
