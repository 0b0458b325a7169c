"""rlexp's child processes end with their parent (``runtime/signals.die_with_parent``, the one
helper the eval worker, the overlap child, the ``gymnasium_async`` workers and a local sweep's jobs
call): the signal they ask for comes when the parent is SIGKILLed, and at once where the parent was
gone before the call (the race ``PR_SET_PDEATHSIG`` alone leaves open), with or without prctl; and
they start with the stop signals held (``blocked``)."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path

import pytest
from test_children import _alive  # running or stopped; a zombie counts as ended

from conftest import REPO

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")

#: The child: ``die_with_parent(parent, SIG)``, then "ready" in its file; a SIGTERM it gets writes
#: "SIGTERM" there and ends it. ``orphan``: it first waits until its parent is gone (the race);
#: ``noprctl``: a platform without prctl.
CHILD = """
import ctypes, os, signal, sys, time
from pathlib import Path
sig, parent, out, *how = signal.Signals[sys.argv[1]], int(sys.argv[2]), Path(sys.argv[3]), *sys.argv[4:]
signal.signal(signal.SIGTERM, lambda *_: (out.write_text("SIGTERM"), os._exit(0)))
if "noprctl" in how:
    def no_libc(*a, **k):
        raise OSError("no prctl here")
    ctypes.CDLL = no_libc
while "orphan" in how and os.getppid() == parent:
    time.sleep(0.01)
from rlexp.runtime.signals import die_with_parent
die_with_parent(parent, sig)
out.write_text("ready")
time.sleep(120)
"""

#: The parent: starts the child, writes its PID, then waits to be killed (``exit``: ends at once).
PARENT = """
import os, subprocess, sys, time
from pathlib import Path
child_py, sig, out, pid_file, *how = sys.argv[1:]
child = subprocess.Popen([sys.executable, child_py, sig, str(os.getpid()), out, *how])
Path(pid_file).write_text(str(child.pid))
if "orphan" in how:
    os._exit(0)
time.sleep(120)
"""


def _wait_for(check, timeout: float = 60) -> bool:
    deadline = time.monotonic() + timeout
    while not check() and time.monotonic() < deadline:
        time.sleep(0.02)
    return check()


def _start(tmp_path: Path, children, sig: str, *how: str):
    """The parent process (recorded: teardown kills its group, the child included), the child's
    PID and the file the child writes to."""
    (tmp_path / "child.py").write_text(CHILD)
    (tmp_path / "parent.py").write_text(PARENT)
    out, pid_file = tmp_path / "out.txt", tmp_path / "pid.txt"
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    parent = children.popen(
        [sys.executable, str(tmp_path / "parent.py"), str(tmp_path / "child.py"), sig, str(out),
         str(pid_file), *how],
        env=env,
    )  # fmt: skip
    assert _wait_for(lambda: pid_file.exists() and pid_file.read_text()), "no child started"
    return parent, int(pid_file.read_text()), out


@pytest.mark.parametrize("sig", ["SIGKILL", "SIGTERM"])
def test_a_child_gets_its_signal_when_its_parent_is_sigkilled(tmp_path, children, sig):
    parent, child, out = _start(tmp_path, children, sig)
    assert _wait_for(lambda: out.exists() and out.read_text() == "ready"), "the child never ran"
    assert _alive(child)
    parent.kill()  # SIGKILL: the parent cleans nothing up
    parent.wait(timeout=30)
    assert _wait_for(lambda: not _alive(child), 30), "the child outlived its SIGKILLed parent"
    assert out.read_text() == ("SIGTERM" if sig == "SIGTERM" else "ready")


@pytest.mark.parametrize("prctl", ["prctl", "noprctl"])
@pytest.mark.parametrize("sig", ["SIGKILL", "SIGTERM"])
def test_a_child_whose_parent_ended_before_the_call_gets_its_signal_at_once(
    tmp_path, children, sig, prctl
):
    """The parent exits before the child calls the helper: no parent-death signal will ever come,
    so the helper sends it itself (also where there is no prctl)."""
    parent, child, out = _start(tmp_path, children, sig, "orphan", prctl)
    parent.wait(timeout=30)
    assert _wait_for(lambda: not _alive(child), 30), "an orphaned child went on running"
    assert not out.exists() or out.read_text() == "SIGTERM"  # never "ready": it ended in the call
    if sig == "SIGTERM":
        assert out.read_text() == "SIGTERM"


def test_without_prctl_a_child_whose_parent_lives_goes_on(tmp_path, children):
    parent, child, out = _start(tmp_path, children, "SIGTERM", "noprctl")
    assert _wait_for(lambda: out.exists() and out.read_text() == "ready"), "the child never ran"
    assert _alive(child) and parent.poll() is None


def test_every_child_process_of_rlexp_sets_its_parent_death_signal_through_the_one_helper():
    """No second copy of the prctl call: the eval worker, the overlap child, the gymnasium_async
    workers and the sweep's jobs call ``die_with_parent``."""
    src = REPO / "src" / "rlexp"
    callers = {
        p.relative_to(src).as_posix() for p in src.rglob("*.py") if "prctl(" in p.read_text()
    }
    assert callers == {"runtime/signals.py"}
    users = {
        p.relative_to(src).as_posix()
        for p in src.rglob("*.py")
        if "die_with_parent(" in p.read_text() and p.name != "signals.py"
    }
    assert users == {
        "training/eval_worker.py",
        "training/overlap.py",
        "envs/gym_worker.py",
        "launch/job_pool.py",
    }


def test_a_child_started_while_signals_are_blocked_inherits_them_and_none_is_lost(children):
    """``blocked``, used while rlexp's children start: the child starts with the signals blocked
    (SigBlk in /proc), and one that reaches this thread meanwhile is handled when the block ends."""
    from rlexp.runtime.signals import blocked

    got: list[int] = []
    previous = signal.signal(signal.SIGUSR1, lambda signum, frame: got.append(signum))
    try:
        with blocked((signal.SIGUSR1, signal.SIGHUP)):
            child = children.popen([sys.executable, "-c", "import time; time.sleep(60)"])
            # to this thread: a signal sent to the process may go to another thread (one a test
            # before this left running) that does not block it
            signal.pthread_kill(threading.get_ident(), signal.SIGUSR1)
            assert got == []
        assert got == [signal.SIGUSR1]
    finally:
        signal.signal(signal.SIGUSR1, previous)
    status = Path(f"/proc/{child.pid}/status").read_text()
    mask = int(next(x for x in status.splitlines() if x.startswith("SigBlk:")).split()[1], 16)
    assert {s for s in signal.Signals if mask >> (s - 1) & 1} == {signal.SIGUSR1, signal.SIGHUP}
