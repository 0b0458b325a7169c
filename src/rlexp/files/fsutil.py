"""The two file-system primitives every writer of a run dir or a sweep dir uses: one atomic write,
and one lock that says who holds it.

``atomic_write``: the data goes to a temporary file beside the target (created exclusively, never
through a link), is flushed to disk (``fsync``, by default), then renamed over the target, and the
directory entry is synced too: a reader (``rlexp runs``, a sweep deciding what to re-run, a resume)
sees the old file or the new one, never half of one, and after a crash or power loss the new one
is there or the old one is. A write that fails leaves no temporary file (``clean_temp_files``
removes those a SIGKILL left). Checkpoints, ``status.json``, ``heartbeat.json`` (not synced: it is
rewritten every few seconds and only says the process lives), exported policies, event outputs and
``multirun.yaml`` all go through it.

``HolderLock``: an exclusive ``flock`` on a lock file that also holds the holder's PID, host and
start, so the one refused can say who has it; the kernel drops it when its process dies, however
it dies. The run-dir lock, the Optuna sweep lock and the sweep-dir claim are each one.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from collections.abc import Callable
from pathlib import Path


def step_file_name(exp_name: str, global_step: int) -> str:
    """A step checkpoint's file name (``rlexp.checkpoints.files.checkpoint_path``), here without torch:
    the run-dir checks before training (``rlexp.run.writable``) size it."""
    return f"{exp_name}_step_{global_step:09d}.pt"


def temp_path(path: Path, keep_suffix: bool = False) -> Path:
    """The temporary file ``atomic_write`` writes ``path`` through: hidden, in the same folder
    (a rename within one file system), named after this process (``.status.json.tmp-1234``;
    ``keep_suffix``: ``.policy.tmp-1234.onnx``, for writers that choose the format by suffix)."""
    if keep_suffix:
        return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def atomic_write(
    path: Path,
    write: Callable[[Path], None],
    *,
    fsync: bool = True,
    keep_suffix: bool = False,
) -> None:
    """``write(tmp)`` writes the data to ``tmp``; then it replaces ``path`` in one rename (see the
    module's docstring). Whatever ``write`` raises is raised, with no temporary file left."""
    path = Path(path)
    tmp = temp_path(path, keep_suffix)
    tmp.unlink(missing_ok=True)  # a leftover of this PID from before a reboot
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644))
    try:
        write(tmp)
        if fsync:
            _fsync(tmp, os.O_RDONLY)
        os.replace(tmp, path)
        if fsync:
            _fsync(path.parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_text(path: Path, text: str, *, fsync: bool = True) -> None:
    """``atomic_write`` of a text (UTF-8)."""
    atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"), fsync=fsync)


def _fsync(path: Path, flags: int) -> None:
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    except OSError:
        if flags & getattr(os, "O_DIRECTORY", 0) == 0:
            raise  # a directory that cannot be synced (some network file systems) is no failure
    finally:
        os.close(fd)


class HolderBusy(OSError):
    """The lock is held by another live process; ``holder`` says which."""

    def __init__(self, path: Path, holder: str) -> None:
        super().__init__(f"{path} is held by {holder}")
        self.path, self.holder = path, holder


class HolderLock:
    """An exclusive ``flock`` on ``path`` that records its holder (``acquire``, ``release``, or
    ``with``); ``blocking``: wait for it instead of raising ``HolderBusy``."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._fd: int | None = None

    def acquire(self, blocking: bool = False) -> HolderLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
        except OSError:
            holder = read_holder(fd)
            os.close(fd)
            raise HolderBusy(self.path, holder) from None
        who = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(who) + "\n").encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        """Drop the lock (idempotent); the file stays (removing it would race the next holder)."""
        if self._fd is None:
            return
        try:
            os.ftruncate(self._fd, 0)
        except OSError:
            pass
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> HolderLock:
        return self if self.held else self.acquire()  # ``with lock.acquire(blocking=True):``

    def __exit__(self, *exc: object) -> None:
        self.release()


def read_holder(fd: int) -> str:
    """``PID 1234 on host node7, since 2026-11-23T10:00:00+0000`` from a lock file's contents."""
    try:
        info = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
        return f"PID {info['pid']} on host {info['host']}, since {info['started']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "holder unknown"
