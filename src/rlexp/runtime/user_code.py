"""User code that raises ``SystemExit`` or ``KeyboardInterrupt`` (an env's ``step``/``reset``, its
module's import, its ``set_state``) fails like any other error of that code: ``failed``, one line
naming what was raised and where, exit 1 (exit 2 where it happens while the run is built).

``sys.exit(0)`` in an env's ``step`` used to end the run with exit 0 and ``status.json`` saying
``running``; in a sweep, the later jobs never ran. Both exceptions derive from ``BaseException``, so
every ``except Exception`` let them through. :func:`user_code_exits` wraps the places where rlexp
runs user code (the config check's and the run's build, the training loop, ``rlexp eval``'s
episodes) and turns them into :class:`UserCodeExit`, an ``Exception``.

A real Ctrl-C is not user code: rlexp's own signal handlers raise :class:`SignalInterrupt`
(``runtime/entry.py``), which passes through untouched, as does a
``KeyboardInterrupt`` while Python's default SIGINT handler is in place (there it may be the
terminal's).
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager

from rlexp.config.rules import first_line
from rlexp.runtime.entry import SignalInterrupt


class UserCodeExit(RuntimeError):
    """``SystemExit`` / ``KeyboardInterrupt`` raised by user code; the message says what and where."""


def describe(exc: BaseException) -> str:
    """What was raised, as one line: its type and message, and where (the innermost frame)."""
    if isinstance(exc, SystemExit):
        line = f"SystemExit({exc.code!r})"
    else:
        name, text = type(exc).__name__, first_line(exc)  # (text: the name where it has none)
        line = name if text == name else f"{name}: {text}"
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    if tb is not None:
        code = tb.tb_frame.f_code
        line += f" (raised in {code.co_name}() at {code.co_filename}:{tb.tb_lineno})"
    return line


def from_user_code(exc: BaseException) -> bool:
    """Whether ``exc`` (a SystemExit or KeyboardInterrupt) came from user code, not a signal."""
    if isinstance(exc, SystemExit):
        return True
    if not isinstance(exc, KeyboardInterrupt) or isinstance(exc, SignalInterrupt):
        return False
    try:  # under Python's own handler a KeyboardInterrupt may be the terminal's Ctrl-C
        return signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    except ValueError:  # not the main thread
        return True


@contextmanager
def user_code_exits(what: str) -> Iterator[None]:
    """Within: a ``SystemExit`` or a user code's ``KeyboardInterrupt`` becomes ``UserCodeExit``
    (``what``: the part of the run, e.g. "the training loop")."""
    try:
        yield
    except (SystemExit, KeyboardInterrupt) as exc:
        if not from_user_code(exc):
            raise
        raise UserCodeExit(
            f"user code raised {describe(exc)} in {what}: an env must raise an exception, not "
            "exit or interrupt; the run counts it as failed"
        ) from None
