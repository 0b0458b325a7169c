"""A live console progress line (rich): steps, steps/s and the recent episode return.

While the bar is live, log records that would be written to the terminal go through the bar's
console instead (``console.print`` puts them above the bar): Hydra's console ``StreamHandler``
holds the real ``sys.stdout``, and writing to it directly draws the record into the bar's line
(``... 0:00:25[2026-11-23 11:07:05,024][rlexp.training.trainer][INFO] - [train] step=...``). The handlers'
streams are restored when the bar ends; file handlers (``train.log``) are never touched.
"""

from __future__ import annotations

import logging
import sys
from typing import IO, TYPE_CHECKING, Any

if TYPE_CHECKING:  # rich is imported when a bar is shown (runs off a terminal never load it)
    from rich.console import Console
    from rich.progress import Progress as RichProgress


class ConsoleStream:
    """A text stream for a logging handler that prints whole lines through a rich console (ANSI
    colours kept), so that they appear above a live display instead of inside it."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self._partial = ""

    def write(self, text: str) -> int:
        from rich.text import Text

        self._partial += text
        *lines, self._partial = self._partial.split("\n")
        for line in lines:
            self.console.print(Text.from_ansi(line), soft_wrap=True, highlight=False)
        return len(text)

    def flush(self) -> None:
        if self._partial:
            self.write("\n")

    def isatty(self) -> bool:
        return True


def terminal_handlers() -> list[logging.StreamHandler]:
    """Every logging handler, on any logger, that writes to a terminal (not files: a
    ``FileHandler`` is a ``StreamHandler`` too, and is left alone)."""
    loggers: list[Any] = [logging.getLogger()]
    loggers += [
        x for x in logging.Logger.manager.loggerDict.values() if isinstance(x, logging.Logger)
    ]
    found: list[logging.StreamHandler] = []
    for lg in loggers:
        for h in lg.handlers:
            if not isinstance(h, logging.StreamHandler) or isinstance(h, logging.FileHandler):
                continue
            isatty = getattr(h.stream, "isatty", None)
            try:
                on_terminal = bool(isatty()) if callable(isatty) else False
            except (OSError, ValueError):  # a closed stream
                on_terminal = False
            if on_terminal and h not in found:
                found.append(h)
    return found


class Progress:
    """Shown only on a terminal (and when enabled); otherwise a no-op, the log lines carry progress.

    ``console``: where the bar is drawn (default: a rich console on stderr, the stream whose
    terminal enables the bar); given, the bar is shown on it whatever the streams are.
    """

    def __init__(
        self, total: int, enabled: bool = True, start: int = 0, console: Console | None = None
    ) -> None:
        self.enabled = enabled and (console is not None or sys.stderr.isatty())
        self.console = console
        self._bar: RichProgress | None = None
        self._task = None
        self._redirected: list[tuple[logging.StreamHandler, IO[str]]] = []
        self._stream: ConsoleStream | None = None
        self.total = total
        self.start = start

    def __enter__(self) -> Progress:
        if self.enabled:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )
            from rich.progress import Progress as RichProgress

            self.console = self.console or Console(file=sys.stderr)
            self._bar = RichProgress(
                TextColumn("[bold]train"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("steps  {task.fields[sps]:>6} sps  return {task.fields[ret]}"),
                TimeElapsedColumn(),
                TimeRemainingColumn(),
                console=self.console,
                transient=False,
            )
            self._bar.__enter__()
            self._task = self._bar.add_task(
                "train", total=self.total, completed=self.start, sps="-", ret="-"
            )
            self._stream = ConsoleStream(self.console)
            for handler in terminal_handlers():
                self._redirected.append((handler, handler.setStream(self._stream)))
        return self

    def update(self, step: int, sps: float, ret: float | None) -> None:
        """Steps done so far: past the budget (the last batch overshoots it) the bar shows the
        real count, ``61440/60000``."""
        if self._bar is not None:
            ret_s = "-" if ret is None else f"{ret:.2f}"
            self._bar.update(self._task, completed=step, sps=f"{sps:.0f}", ret=ret_s)

    def __exit__(self, *exc: object) -> None:
        if self._bar is None:
            return
        try:
            if self._stream is not None:
                self._stream.flush()
            for handler, stream in reversed(self._redirected):
                handler.setStream(stream)
            self._redirected = []
        finally:
            self._bar.__exit__(*exc)
            self._bar = None
