"""The entry points' last guard (``python train.py``, ``rlexp ...``, ``python -m rlexp``): faults of
the environment end in one line on stderr and the documented exit code, never a traceback.

* the working directory was deleted (``os.getcwd()`` fails): exit 2 before anything is imported;
* Ctrl-C before a run trains (imports, config composition, building; between a sweep's jobs):
  exit 130, nothing to save (a run that trains handles it itself: ``runtime/signals.py``);
* an ``OSError`` that escaped (a path that cannot be created, read or written): exit 2, naming the
  path and the reason (runs turn the ones met while training into ``failed``, exit 1, first);
  ``rlexp.app`` sets ``HYDRA_FULL_ERROR`` so that those met inside Hydra (a sweep's job dir that
  cannot be created) reach this guard too, instead of Hydra's traceback;
* :class:`EntryError`: a known fault found by a check, exit 2;
* Hydra's compact errors (a config that does not compose): its own message, exit 1, as Hydra does.

Anything else is a bug in rlexp or a library: it keeps its full traceback, for the bug report.
"""

from __future__ import annotations

import errno
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

EXIT_BAD_INPUT = 2  # rlexp.run.rundir.EXIT_CONFIG (not imported: this module stays light)
EXIT_SIGINT = 130


class SignalInterrupt(KeyboardInterrupt):
    """The ``KeyboardInterrupt`` rlexp's own SIGINT handlers raise (``outside_run``, ``signals``):
    a real Ctrl-C, told apart from one that user code raises (``rlexp.runtime.user_code``)."""


#: Set when rlexp's start-up SIGINT handler (``outside_run``) raised its ``SignalInterrupt``: the
#: user pressed Ctrl-C, whatever error the code it landed in turned that into.
_SIGINT_RAISED = [False]


def note_sigint(raised: bool = True) -> None:
    """Record that the start-up Ctrl-C handler raised (False: a new process state, ``install``)."""
    _SIGINT_RAISED[0] = raised


def interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` came out of a Ctrl-C: its cause/context chain holds a ``KeyboardInterrupt``,
    or rlexp's start-up handler raised one in this process (``note_sigint``). A Ctrl-C at start-up
    that landed inside a library surfaces as that library's error: a C extension's module init
    (pybind11's, MuJoCo's) turns it into ``ImportError: initialization failed`` chained to the
    interrupt, a library's failing ``finally`` into its own error, and C code that clears the
    error and raises its own into one with no chain at all."""
    if _SIGINT_RAISED[0]:
        return True
    seen: set[int] = set()
    link: BaseException | None = exc
    while link is not None and id(link) not in seen:
        if isinstance(link, KeyboardInterrupt):
            return True
        seen.add(id(link))
        link = link.__cause__ or link.__context__
    return False


class EntryError(Exception):
    """A fault of the environment a check found; its message is the whole line."""


def check_cwd() -> None:
    """``EntryError`` when the working directory no longer exists (deleted, or its mount gone):
    relative paths (``outputs/``, the config dir) cannot be resolved, and torch's MKL refuses to
    load with a misleading message."""
    try:
        os.getcwd()
    except OSError as exc:
        raise EntryError(
            f"the working directory no longer exists ({exc.strerror}; it was deleted or moved "
            "while this shell was in it): cd to an existing directory and run the command again"
        ) from None


def _say(prog: str, message: str, code: int) -> None:
    sys.stdout.flush()
    print(f"{prog}: {message}", file=sys.stderr, flush=True)
    sys.exit(code)


def os_error_line(exc: OSError) -> str:
    """An ``OSError`` as one line: the path(s) it names and why."""
    where = " -> ".join(str(p) for p in (exc.filename, exc.filename2) if p is not None)
    why = exc.strerror or str(exc)
    return f"{where}: {why}" if where else why


def run_dir_error(run_dir: object, exc: OSError) -> str:
    """One line for a run dir that could not be created, read or written before training."""
    return f"run dir {run_dir} cannot be used: {os_error_line(exc)}; use another hydra.run.dir"


_INTERRUPTED = "interrupted (Ctrl-C) while no run was training: nothing to save"


@contextmanager
def entry_guard(prog: str) -> Iterator[None]:
    """Run the body of an entry point under the rules above."""
    try:
        check_cwd()
        yield
    except KeyboardInterrupt:
        _say(prog, _INTERRUPTED, EXIT_SIGINT)
    except EntryError as exc:
        _say(prog, str(exc), EXIT_BAD_INPUT)
    except Exception as exc:
        if interrupted(exc):  # a Ctrl-C that a library turned into its own error
            _say(prog, _INTERRUPTED, EXIT_SIGINT)
        if _hydra_compact(exc):  # Hydra's own one-liners (rlexp.app lets them through: see there)
            sys.stderr.write("\n".join(_hydra_lines(exc)) + "\n")
            sys.exit(1)
        if not isinstance(exc, OSError):
            raise  # a bug: its traceback is what a report needs
        if exc.errno == errno.EPIPE:  # `rlexp runs | head`: the reader left; say nothing more
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            sys.exit(0)
        _say(prog, os_error_line(exc), EXIT_BAD_INPUT)


def _hydra_compact(exc: BaseException) -> bool:
    """An error Hydra prints as its message alone (a config that does not compose)."""
    errors = sys.modules.get("hydra.errors")
    return errors is not None and isinstance(exc, errors.CompactHydraException)


def _hydra_lines(exc: BaseException) -> list[str]:
    """What Hydra itself prints for it: its message, and the OmegaConf error it wraps."""
    lines = [str(exc)]
    omegaconf_errors = sys.modules.get("omegaconf.errors")
    cause = exc.__cause__
    if omegaconf_errors is not None and isinstance(cause, omegaconf_errors.OmegaConfBaseException):
        lines.append(str(cause))
    return lines
