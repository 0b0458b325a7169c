"""One atomic write and one holder lock for every writer (#30 item 15): status.json is synced
(sweeps and resumes decide from it), a failed write leaves nothing, a link is replaced and never
followed, and a busy lock names its holder."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import textwrap

import pytest

from conftest import REPO
from rlexp.files import fsutil
from rlexp.files.fsutil import HolderBusy, HolderLock, atomic_write, atomic_write_text
from rlexp.run.rundir import RunDirBusy, RunDirLock, write_status


def test_atomic_write_replaces_a_link_and_leaves_no_temporary_file(tmp_path):
    target, elsewhere = tmp_path / "status.json", tmp_path / "elsewhere.txt"
    elsewhere.write_text("theirs")
    target.symlink_to(elsewhere)
    atomic_write_text(target, "mine")
    assert not target.is_symlink() and target.read_text() == "mine"
    assert elsewhere.read_text() == "theirs"  # the link was replaced, not followed
    assert sorted(p.name for p in tmp_path.iterdir()) == ["elsewhere.txt", "status.json"]


def test_a_failed_write_keeps_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "policy.onnx"
    target.write_text("old")

    def half_then_fail(tmp):
        assert tmp.name == f".policy.tmp-{os.getpid()}.onnx"  # the suffix kept for the writer
        tmp.write_text("half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space left"):
        atomic_write(target, half_then_fail, keep_suffix=True)
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["policy.onnx"]


def test_status_json_is_synced_file_and_folder_and_the_heartbeat_is_not(tmp_path, monkeypatch):
    synced = []
    real = os.fsync
    monkeypatch.setattr(
        os, "fsync", lambda fd: (synced.append(os.readlink(f"/proc/self/fd/{fd}")), real(fd))[1]
    )
    write_status(tmp_path, "running", 512)
    assert synced == [str(tmp_path / f".status.json.tmp-{os.getpid()}"), str(tmp_path)]
    assert json.loads((tmp_path / "status.json").read_text())["global_step"] == 512
    synced.clear()
    atomic_write_text(tmp_path / "heartbeat.json", "{}", fsync=False)
    assert synced == []


def test_a_busy_lock_names_its_holder_and_the_kernel_drops_it_with_its_process(tmp_path):
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import sys, time
            sys.path.insert(0, {str(REPO / 'src')!r})
            from rlexp.files.fsutil import HolderLock
            HolderLock({str(tmp_path / 'x.lock')!r}).acquire()
            print("held", flush=True)
            time.sleep(60)
        """)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(HolderBusy) as busy:
            HolderLock(tmp_path / "x.lock").acquire()
        assert busy.value.holder.startswith(f"PID {holder.pid} on host ")
        run = RunDirLock(tmp_path)
        run.path = tmp_path / "x.lock"  # the run-dir lock is the same lock
        run._lock = HolderLock(run.path)
        with pytest.raises(RunDirBusy, match=rf"is in use by another run \(PID {holder.pid} "):
            run.acquire()
    finally:
        holder.kill()
        holder.wait(timeout=30)
    with HolderLock(tmp_path / "x.lock") as lock:  # gone with its process, however it died
        assert lock.held


def test_there_is_one_atomic_write_and_one_lock_in_the_code():
    """No other module renames a temporary file into place or takes an flock itself."""
    allowed_replace = {"fsutil.py", "files.py", "policy_eval.py"}  # moving aside, not writing
    for path in (REPO / "src" / "rlexp").rglob("*.py"):
        tree = ast.parse(path.read_text())
        calls = {
            f"{node.func.value.id}.{node.func.attr}"
            for node in ast.walk(tree)
            if isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and isinstance(node.func.value, ast.Name)
        }
        if path.name != "fsutil.py":
            assert "fcntl.flock" not in calls, f"{path.name} takes an flock of its own"
        if path.name not in allowed_replace:
            assert "os.replace" not in calls, f"{path.name} renames a file into place itself"
    assert fsutil.__doc__ and "atomic_write" in fsutil.__doc__


def test_a_blocking_acquire_in_a_with_block_takes_the_lock_once(tmp_path):
    with HolderLock(tmp_path / "claim.lock").acquire(blocking=True) as lock:
        assert lock.held
        with pytest.raises(HolderBusy):  # another open of the file: refused while held
            HolderLock(tmp_path / "claim.lock").acquire()
    assert not lock.held
