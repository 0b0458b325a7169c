"""The ``children`` fixture (tests/conftest.py): what a test starts is ended on teardown, its own
children included, pass or fail; and it starts with the stop signals a terminal delivers, whatever
dispositions the test runner inherited (``&`` and ``nohup`` ignore SIGINT / SIGHUP)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import REPO, Children

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")


def _alive(pid: int) -> bool:
    """Running or stopped; a zombie (dead, its parent not yet reaped it) counts as ended."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _wait_gone(pids: list[int], timeout: float = 10) -> list[int]:
    deadline = time.time() + timeout
    while any(map(_alive, pids)) and time.time() < deadline:
        time.sleep(0.05)
    return [p for p in pids if _alive(p)]


def _read_pids(path: Path, timeout: float = 10) -> list[int]:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if path.exists() and path.read_text().endswith("\n"):
            return [int(p) for p in path.read_text().split()]
        time.sleep(0.05)
    raise AssertionError(f"{path} was never written")


#: A shell that starts a grandchild, writes both PIDs to $1 and waits: a train.py with its workers.
FAMILY = ["sh", "-c", 'sleep 600 & echo "$$ $!" > "$1"; wait', "family"]


def test_kill_all_ends_the_whole_process_group(tmp_path):
    started = Children()
    proc = started.popen([*FAMILY, str(tmp_path / "pids")])
    pids = _read_pids(tmp_path / "pids")
    assert pids[0] == proc.pid and os.getpgid(pids[1]) == proc.pid, "not a group of its own"
    started.kill_all()
    assert proc.returncode == -signal.SIGKILL
    assert _wait_gone(pids) == [], "a process of the group survived"


def test_a_test_that_fails_before_it_signals_its_child_leaves_nothing_running(tmp_path):
    """The run-dir-lock test once failed before its SIGTERM and left a 100M-frame train.py behind."""
    pid_file = tmp_path / "pids"
    (tmp_path / "test_inner.py").write_text(
        f"def test_fails_early(children):\n"
        f"    children.popen({[*FAMILY, str(pid_file)]!r})\n"
        f"    import time\n"
        f"    while not __import__('os').path.exists({str(pid_file)!r}):\n"
        f"        time.sleep(0.05)\n"
        f"    assert False, 'failed before it signalled its child'\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO / "src")])}
    inner = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "conftest", "-p", "no:cacheprovider",
         "--rootdir", str(tmp_path), str(tmp_path / "test_inner.py")],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert inner.returncode == 1, inner.stdout + inner.stderr
    assert "failed before it signalled its child" in inner.stdout
    assert _wait_gone(_read_pids(pid_file)) == [], "left running after the failed test"


def test_children_start_with_the_default_stop_signals_whatever_this_process_ignores(tmp_path):
    report = (  # SIGINT, SIGTERM, SIGHUP in a new Python: ignored, or as a terminal delivers them
        "import signal as s; print(' '.join('ignored' if s.getsignal(n) == s.SIG_IGN else 'default'"
        " if s.getsignal(n) in (s.SIG_DFL, s.default_int_handler) else 'other' for n in (2, 15, 1)))"
    )
    ignored = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGHUP)}
    started = Children()
    try:
        plain = subprocess.run([sys.executable, "-c", report], capture_output=True, text=True)
        ours = started.popen([sys.executable, "-c", report], stdout=subprocess.PIPE, text=True)
        out, _ = ours.communicate(timeout=60)
    finally:
        for sig, previous in ignored.items():
            signal.signal(sig, previous)
        started.kill_all()
    assert plain.stdout.split() == ["ignored", "default", "ignored"], (
        "an ignored signal survives exec"
    )
    assert out.split() == ["default", "default", "default"]


def test_a_train_py_left_running_at_the_end_of_the_session_fails_it_and_is_killed(tmp_path):
    """conftest's session guard: a test that starts train.py without ``children`` and leaves it
    running passes on its own; the session ends in an error naming it, and it is killed."""
    pid_file = tmp_path / "pid"
    (tmp_path / "train.py").write_text("import time\ntime.sleep(600)\n")
    (tmp_path / "test_inner.py").write_text(
        f"import subprocess, sys\n"
        f"def test_leaks():\n"
        f"    proc = subprocess.Popen([sys.executable, {str(tmp_path / 'train.py')!r}])\n"
        f"    open({str(pid_file)!r}, 'w').write(f'{{proc.pid}}\\n')\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO / "src")])}
    try:
        inner = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "conftest", "-p", "no:cacheprovider",
             "--rootdir", str(tmp_path), str(tmp_path / "test_inner.py")],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        pid = _read_pids(pid_file)[0]
        assert inner.returncode == 1, inner.stdout + inner.stderr
        assert "1 passed, 1 error" in inner.stdout, inner.stdout
        assert "train.py process(es) started by this test session still ran" in inner.stdout
        assert f"PID {pid}:" in inner.stdout
        assert _wait_gone([pid]) == [], "the guard did not kill it"
    finally:
        if pid_file.exists():
            with contextlib.suppress(ProcessLookupError, ValueError):
                os.kill(int(pid_file.read_text()), signal.SIGKILL)
