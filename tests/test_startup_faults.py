"""Start-up and shut-down paths outside training (#29 items 9 and 10): each ends in one line and the
documented exit code, never a traceback, and writes nothing where it says nothing is written.

Item 9: a run dir that cannot be created or written (a path through a file, a name or a path too
long for the filesystem, a read-only ``outputs/``, a read-only run dir on resume or for ``rlexp
export``), a deleted working directory, a ``MUJOCO_GL`` whose library is missing, Ctrl-C in the first
seconds of start-up or between two jobs of a sweep. Item 10: a stop signal after the final status,
a launch refused while Hydra already had its log file open in the winner's dir, a video cut short by
a full disk.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from conftest import CONF_DIR, REPO, SHORT, SWEEP_TINY, Children

TRAIN = str(REPO / "train.py")


def _env(**extra: str) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO / "src"), "MUJOCO_GL": "egl", **extra}


def _launch(
    children: Children, args: list[str], cwd: Path, timeout: float = 240, **env: str
) -> subprocess.CompletedProcess:
    """Run ``args`` (a command) through ``children`` and wait: its exit code, stdout, stderr."""
    proc = children.popen(
        args, cwd=cwd, env=_env(**env), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    out, err = proc.communicate(timeout=timeout)
    return subprocess.CompletedProcess(args, proc.returncode, out, err)


def _one_line(proc: subprocess.CompletedProcess, *needles: str) -> str:
    """The single line of ``proc``'s stderr; no traceback anywhere; each needle in that line."""
    both = proc.stdout + proc.stderr
    assert "Traceback" not in both, both[-4000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr[-4000:]
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def _snapshot(root: Path) -> dict[str, bytes]:
    """Every file below ``root`` (relative path -> content)."""
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


@contextlib.contextmanager
def _read_only(path: Path) -> Iterator[None]:
    """``path`` read-only for this block: chmod for a normal user; as root (whom chmod does not
    stop) a read-only bind mount of it onto itself; skipped where neither is possible."""
    if os.geteuid() != 0:
        modes = {p: p.stat().st_mode for p in [path, *path.rglob("*")] if p.is_dir()}
        for p in modes:
            p.chmod(0o555)
        try:
            yield
        finally:
            for p, mode in modes.items():
                p.chmod(mode)
        return
    if not shutil.which("mount"):
        pytest.skip("root without mount(8): cannot make a read-only dir here")
    ok = subprocess.run(["mount", "--bind", str(path), str(path)], capture_output=True)
    if ok.returncode != 0:
        pytest.skip(f"root cannot bind-mount here: {ok.stderr.decode().strip()}")
    try:
        ro = subprocess.run(["mount", "-o", "remount,bind,ro", str(path)], capture_output=True)
        if ro.returncode != 0:
            pytest.skip(f"cannot remount read-only: {ro.stderr.decode().strip()}")
        yield
    finally:
        subprocess.run(["umount", str(path)], check=True)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A finished two-iteration run (checkpoints at steps 256 and 512), to resume and export."""
    root = tmp_path_factory.mktemp("finished")
    run_dir = root / "run"
    with Children() as children:
        proc = _launch(children, [sys.executable, TRAIN, *SHORT, "logger=none", f"hydra.run.dir={run_dir}"], root)  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return run_dir


def _copy_run(finished_run: Path, dest: Path) -> Path:
    shutil.copytree(finished_run, dest, symlinks=True)
    return dest


# -- item 9: run dirs that cannot be created or written -------------------------------------------
def _path_too_long(tmp_path: Path) -> Path:
    """A run dir whose own path fits the filesystem (every name < 255, the whole < 4096) but whose
    checkpoints' paths do not: today it passes the write check and fails at the first save."""
    limit = os.pathconf(tmp_path, "PC_PATH_MAX") - 1  # 4095 on Linux
    parent = tmp_path
    while len(str(parent)) < limit - 300:
        parent = parent / ("p" * 200)
    parent.mkdir(parents=True)
    # 45 characters left: ".rlexp.lock", "train.log", "checkpoints/" fit; the checkpoint's
    # "checkpoints/.InvertedPendulum-v5_ppo_step_000000256.pt.tmp-<pid>" does not
    run_dir = parent / ("r" * (limit - len(str(parent)) - 1 - 45))
    assert len(str(run_dir)) == limit - 45
    return run_dir


@pytest.mark.parametrize("case", ["through_a_file", "name_too_long", "path_too_long", "read_only_outputs"])  # fmt: skip
def test_a_run_dir_that_cannot_be_created_or_written_is_one_line_and_exit_2(
    tmp_path, children, case
):
    (tmp_path / "afile").write_text("a regular file")
    args = [sys.executable, TRAIN, *SHORT, "logger=none"]
    watched = tmp_path
    if case == "through_a_file":
        run_dir = tmp_path / "afile" / "run"
        needle = "not a folder"
    elif case == "name_too_long":
        run_dir = tmp_path / "outputs" / ("n" * 300)
        needle = "a name in it has 300 bytes"
    elif case == "path_too_long":
        run_dir = _path_too_long(tmp_path)
        watched = run_dir.parent
        needle = "the run's checkpoints there would have paths of"
    if case == "read_only_outputs":
        (tmp_path / "outputs").mkdir()
        before = _snapshot(tmp_path)
        with _read_only(tmp_path / "outputs"):  # the default hydra.run.dir: outputs/<date>/<time>
            proc = _launch(children, args, tmp_path)
        line = _one_line(proc, "config error: hydra.run.dir (the run dir)", str(tmp_path / "outputs"))  # fmt: skip
        assert "Read-only file system" in line or "Permission denied" in line, line
        assert list((tmp_path / "outputs").iterdir()) == []
    else:
        before = _snapshot(watched)
        proc = _launch(children, [*args, f"hydra.run.dir={run_dir}"], tmp_path)
        _one_line(proc, "config error: hydra.run.dir (the run dir)", str(run_dir), needle)
        assert not run_dir.exists()
    assert proc.returncode == 2, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert _snapshot(watched) == before, "something was written"


def test_a_sweep_dir_that_cannot_be_created_or_a_read_only_job_dir_is_refused_before_hydra(
    tmp_path,
):
    """Not only run dirs: the sweep dir Hydra creates, and the job dir a re-run writes into."""
    from rlexp.config.validate import ConfigError
    from rlexp.launch.precheck import precheck

    (tmp_path / "afile").write_text("x")
    sweep = ["-m", *SWEEP_TINY, "logger=none", "seed=1,2"]
    with pytest.raises(ConfigError) as info:
        precheck([*sweep, f"hydra.sweep.dir={tmp_path / 'afile' / 'sweep'}"], CONF_DIR)
    assert str(info.value) == (
        f"hydra.sweep.dir (the sweep dir) {tmp_path / 'afile' / 'sweep'} cannot be written: "
        f"{tmp_path / 'afile'} is a file, not a folder (Not a directory); use another "
        "hydra.sweep.dir, or make it writable"
    )
    assert not (tmp_path / "afile" / "sweep").exists()
    job = tmp_path / "sweep" / "1"  # a job dir of an earlier attempt of this sweep
    job.mkdir(parents=True)
    (job / ".rlexp.lock").write_text("")
    (job / "train.log").mkdir()  # where Hydra opens the job's log file: a traceback otherwise
    with pytest.raises(ConfigError, match=r"train\.log"):
        precheck([*sweep, f"hydra.sweep.dir={tmp_path / 'sweep'}"], CONF_DIR)


def test_a_job_dir_hydra_cannot_create_in_a_sweep_is_one_line_not_hydras_traceback(
    tmp_path, children
):
    """The job dirs are named per job (here a 300-character ``hydra.sweep.subdir``), so only Hydra
    meets the failure: its error reaches the entry guard, one line naming the path."""
    sweep = tmp_path / "sweep"
    subdir = "s" * 300
    args = ["-m", *SHORT, "logger=none", "seed=1,2", f"hydra.sweep.dir={sweep}",
            f"hydra.sweep.subdir={subdir}_${{hydra.job.num}}"]  # fmt: skip
    proc = _launch(children, [sys.executable, TRAIN, *args], tmp_path)
    assert proc.returncode == 2, proc.stdout[-3000:] + proc.stderr[-3000:]
    _one_line(proc, f"train.py: {sweep / subdir}_0: {os.strerror(errno.ENAMETOOLONG)}")
    assert [p.name for p in sweep.iterdir() if p.is_dir()] == []


def test_a_read_only_run_dir_on_resume_is_one_line_and_exit_2(tmp_path, children, finished_run):
    run_dir = _copy_run(finished_run, tmp_path / "run")
    before = _snapshot(run_dir)
    with _read_only(run_dir):
        proc = _launch(
            children,
            [sys.executable, TRAIN, *SHORT, "logger=none", "trainer.total_frames=1024",
             f"hydra.run.dir={run_dir}"],
            tmp_path,
        )  # fmt: skip
    assert proc.returncode == 2, proc.stdout[-3000:] + proc.stderr[-3000:]
    line = _one_line(proc, str(run_dir), "cannot be written")
    assert "Read-only file system" in line or "Permission denied" in line, line
    assert _snapshot(run_dir) == before


def test_rlexp_export_into_a_read_only_run_dir_is_one_line_and_exit_2(
    tmp_path, children, finished_run
):
    run_dir = _copy_run(finished_run, tmp_path / "run")
    with _read_only(run_dir):
        proc = _launch(children, [sys.executable, "-m", "rlexp", "export", str(run_dir)], tmp_path)
    assert proc.returncode == 2, proc.stdout[-3000:] + proc.stderr[-3000:]
    line = _one_line(proc, "rlexp export: cannot write", str(run_dir / "exported"))
    assert "Read-only file system" in line or "Permission denied" in line, line
    assert not (run_dir / "exported").exists()


def test_rlexp_eval_video_into_a_read_only_folder_is_one_line_before_the_episodes(
    tmp_path, children, finished_run
):
    out = tmp_path / "videos"
    out.mkdir()
    with _read_only(out):
        proc = _launch(
            children,
            [sys.executable, "-m", "rlexp", "eval", str(finished_run), "--episodes", "1",
             "--video", str(out / "eval.mp4")],
            tmp_path,
        )  # fmt: skip
    assert proc.returncode == 2, proc.stdout[-3000:] + proc.stderr[-3000:]
    line = _one_line(proc, f"rlexp eval: --video {str(out / 'eval.mp4')!r} cannot be written")
    assert "Read-only file system" in line or "Permission denied" in line, line
    assert "mean return" not in proc.stdout, "the episodes ran before the check"
    assert list(out.iterdir()) == []


def test_a_deleted_working_directory_is_one_line_and_exit_2(tmp_path, children, finished_run):
    gone = tmp_path / "gone"
    commands = {
        "train.py": [sys.executable, TRAIN, *SHORT],
        "rlexp runs": [sys.executable, "-m", "rlexp", "runs"],
        "rlexp eval": [sys.executable, "-m", "rlexp", "eval", str(finished_run), "--episodes", "1"],
    }
    for prog, command in commands.items():
        gone.mkdir()
        # the shell enters the dir, removes it, then runs the command there
        shell = ["sh", "-c", 'cd "$1" && rmdir "$1" && shift && exec "$@"', "sh", str(gone)]
        proc = _launch(children, [*shell, *command], tmp_path, timeout=120)
        assert proc.returncode == 2, (prog, proc.stdout[-2000:], proc.stderr[-2000:])
        _one_line(proc, f"{prog}: the working directory no longer exists", "cd to an existing")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# -- item 9: MUJOCO_GL naming a backend whose library is missing -----------------------------------
def test_gl_problem_names_mujoco_gl_its_value_and_what_works_here(monkeypatch):
    """Unit: egl's libraries absent, osmesa's present (the reverse of most machines)."""
    from rlexp.envs.native import render

    loads = {"EGL": False, "OpenGL": True, "GL": True, "OSMesa": True}
    monkeypatch.setattr(render, "_loads", lambda name: loads[name])
    monkeypatch.delitem(sys.modules, "mujoco.rendering.classic.gl_context", raising=False)
    monkeypatch.setenv("MUJOCO_GL", "egl")
    assert render.gl_problem(rendering=False) == (
        "MUJOCO_GL='egl' needs libEGL, which cannot be loaded here; MUJOCO_GL values that work "
        "here: osmesa"
    )
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    assert render.gl_problem(rendering=False) is None


def _lib_loads(name: str) -> bool:
    """``lib<name>.so`` loads here, looked for as PyOpenGL does."""
    import ctypes

    for filename in (f"lib{name}.so", *(f"lib{name}.so.{i}" for i in range(10))):
        with contextlib.suppress(OSError):
            ctypes.CDLL(filename)
            return True
    return False


def test_mujoco_gl_without_its_library_is_one_line_and_exit_2_before_training(
    tmp_path, children, finished_run
):
    if _lib_loads("OSMesa"):
        pytest.skip("libOSMesa is installed here: MUJOCO_GL=osmesa works")
    works = "MUJOCO_GL values that work here: " + ("egl" if _lib_loads("EGL") else "")
    video = tmp_path / "eval.mp4"
    for gl in ("osmesa", "nonsense"):
        proc = _launch(
            children,
            [sys.executable, "-m", "rlexp", "eval", str(finished_run), "--episodes", "1",
             "--video", str(video)],
            tmp_path, MUJOCO_GL=gl,
        )  # fmt: skip
        assert proc.returncode == 2, proc.stdout[-3000:] + proc.stderr[-3000:]
        _one_line(proc, f"rlexp eval: MUJOCO_GL={gl!r}", works if gl == "osmesa" else "accepts")
    run_dir = tmp_path / "run"
    args = [*SHORT, "logger=none", "events=eval_video", "trainer.eval_every=256",
            "env.num_eval_envs=1", "trainer.eval_episodes=1", f"hydra.run.dir={run_dir}"]  # fmt: skip
    proc = _launch(children, [sys.executable, TRAIN, *args], tmp_path, MUJOCO_GL="osmesa")
    assert proc.returncode == 2, proc.stdout[-3000:] + proc.stderr[-3000:]
    _one_line(proc, "config error: MUJOCO_GL='osmesa' needs libOSMesa", works)
    assert not run_dir.exists() and not video.exists()


# -- item 9: Ctrl-C in the first seconds, and between two jobs of a sweep --------------------------
@pytest.mark.parametrize("delay", [0.2, 0.5, 1.0, 2.0])
def test_ctrl_c_in_the_first_seconds_of_start_up_is_one_line_and_exit_130(
    tmp_path, children, delay
):
    run_dir = tmp_path / "run"
    args = [sys.executable, TRAIN, *SHORT, "logger=none", f"hydra.run.dir={run_dir}"]
    proc = children.popen(
        args, cwd=tmp_path, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=240)
    done = subprocess.CompletedProcess(args, proc.returncode, out, err)
    assert proc.returncode == 130, (out[-3000:], err[-3000:])
    both = out + err
    assert "Traceback" not in both, both[-3000:]
    status = run_dir / "status.json"
    state = json.loads(status.read_text())["state"] if status.exists() else None
    assert state in (None, "interrupted"), state  # never "running"
    if state == "interrupted":  # (a fast machine: the run's own handlers had taken over)
        return
    lines = [ln for ln in both.splitlines() if "interrupted" in ln]
    assert len(lines) == 1, both[-3000:]
    if err.strip():  # before Hydra's logging: the entry point's line on stderr
        _one_line(done, "train.py: interrupted (Ctrl-C)")


_SLOW_CLOSE = """
import sys, time
import rlexp.training.trainer
close = rlexp.training.trainer.Trainer.close
calls = []
def slow_close(self):  # the first job's shut-down, after its final status.json
    close(self)
    calls.append(1)
    if len(calls) == 1:
        print("FINAL-STATUS-WRITTEN", flush=True)
        time.sleep(6)
rlexp.training.trainer.Trainer.close = slow_close
from rlexp.cli import train
train(sys.argv[1:], prog="train.py")
"""


def _wait_for(console: Path, text: str, proc: subprocess.Popen, timeout: float = 240) -> None:
    end = time.monotonic() + timeout
    while text not in console.read_text():
        assert proc.poll() is None, console.read_text()[-3000:]
        assert time.monotonic() < end, console.read_text()[-3000:]
        time.sleep(0.02)


def test_ctrl_c_between_two_jobs_of_a_sweep_stops_it_with_130_before_the_next_job(
    tmp_path, children
):
    (tmp_path / "slow_close.py").write_text(_SLOW_CLOSE)
    sweep = tmp_path / "sweep"
    args = ["-m", *SHORT, "logger=none", "seed=5,6", f"hydra.sweep.dir={sweep}"]
    console = tmp_path / "console.txt"
    with open(console, "w") as f:
        proc = children.popen(
            [sys.executable, str(tmp_path / "slow_close.py"), *args],
            cwd=tmp_path, env=_env(), stdout=f, stderr=subprocess.STDOUT,
        )  # fmt: skip
    _wait_for(console, "FINAL-STATUS-WRITTEN", proc)
    assert json.loads((sweep / "0" / "status.json").read_text())["state"] == "finished"
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=240)
    text = console.read_text()
    assert proc.returncode == 130, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    errors = [ln for ln in text.splitlines() if "[ERROR]" in ln]
    assert len(errors) == 1 and "the sweep stops before job" in errors[0], text[-3000:]
    assert json.loads((sweep / "0" / "status.json").read_text())["state"] == "finished"
    assert not (sweep / "1" / "status.json").exists(), "job 1 started"
    assert not (sweep / "1" / "checkpoints").exists()


# -- item 10 -----------------------------------------------------------------------------------------
_SLOW_EXIT = """
import sys, time
import rlexp.app
prompt_exit = rlexp.app._prompt_exit
def slow_exit():  # after the run's handlers are gone: closing loggers, atexit (W&B's upload)
    print("FINAL-STATUS-WRITTEN", flush=True)
    time.sleep(4)
    prompt_exit()
rlexp.app._prompt_exit = slow_exit
from rlexp.cli import train
train(sys.argv[1:], prog="train.py")
"""


def test_sigterm_after_the_final_status_leaves_exit_0_and_finished_in_agreement(tmp_path, children):
    (tmp_path / "slow_exit.py").write_text(_SLOW_EXIT)
    run_dir = tmp_path / "run"
    console = tmp_path / "console.txt"
    with open(console, "w") as f:
        proc = children.popen(
            [sys.executable, str(tmp_path / "slow_exit.py"), *SHORT, "logger=none",
             f"hydra.run.dir={run_dir}"],
            cwd=tmp_path, env=_env(), stdout=f, stderr=subprocess.STDOUT,
        )  # fmt: skip
    _wait_for(console, "FINAL-STATUS-WRITTEN", proc)
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=120)
    text = console.read_text()
    assert proc.returncode == 0, (proc.returncode, text[-3000:])
    assert json.loads((run_dir / "status.json").read_text())["state"] == "finished"
    assert "Traceback" not in text
    assert "SIGTERM received after the run ended" in text, text[-2000:]


_RACE = """
import sys
import rlexp.run.rundir
# The race: the winner takes the run dir's lock just after this launch's early probe of it.
rlexp.run.rundir.RunDirLock.check = lambda self: None
from rlexp.cli import train
train(sys.argv[1:], prog="train.py")
"""


def test_a_refused_launch_writes_nothing_in_the_winners_dir_not_even_its_train_log(
    tmp_path, children, finished_run
):
    from rlexp.run.rundir import RunDirLock

    (tmp_path / "race.py").write_text(_RACE)
    run_dir = _copy_run(finished_run, tmp_path / "run")
    winner = RunDirLock(run_dir).acquire()  # the run that owns the dir (this test's process)
    try:
        before = _snapshot(run_dir)
        assert "[rlexp.app]" in before["train.log"].decode()
        proc = _launch(
            children,
            [sys.executable, str(tmp_path / "race.py"), *SHORT, "logger=none",
             "trainer.total_frames=1024", f"hydra.run.dir={run_dir}"],
            tmp_path,
        )  # fmt: skip
        assert proc.returncode == 2, proc.stdout[-3000:] + proc.stderr[-3000:]
        assert "is in use by another run" in proc.stdout + proc.stderr
        assert "Traceback" not in proc.stdout + proc.stderr
        after = _snapshot(run_dir)
        assert after["train.log"] == before["train.log"], "the refusal went into the winner's log"
        assert after == before
    finally:
        winner.release()


def _video_frames() -> list:
    import numpy as np

    rng = np.random.default_rng(0)  # noise: it does not compress, so 30 frames fill 64 kB
    return [rng.integers(0, 255, (240, 320, 3), dtype=np.uint8) for _ in range(30)]


def _finalize(run_dir: Path, caplog) -> object:
    from rlexp.events.builtin import RecordVideo
    from rlexp.events.manager import EventContext

    recorder = RecordVideo()
    recorder.frames = _video_frames()
    ctx = EventContext(global_step=256, run_dir=run_dir, event="events.eval.record_video")
    with caplog.at_level(logging.INFO, logger="rlexp.events"):
        recorder.finalize(ctx, name="cam")  # never raises: training goes on
    return recorder


def _check_not_written(recorder, run_dir: Path, caplog) -> None:
    path = run_dir / "videos" / "cam_step_000000256.mp4"
    lines = [r.getMessage() for r in caplog.records if r.name.startswith("rlexp.events")]
    assert len(lines) == 1, lines
    assert lines[0].startswith("[video] not written (30 frames): ")
    assert str(path) in lines[0] and os.strerror(errno.ENOSPC) in lines[0], lines[0]
    assert recorder.written == [] and not path.exists()
    assert list((run_dir / "videos").iterdir()) == [], "a temporary file was left"


def test_a_video_write_refused_with_enospc_is_one_warning_and_training_goes_on(
    tmp_path, caplog, monkeypatch
):
    import imageio.v2 as imageio

    class FullDisk:
        def __init__(self, path, **kw):
            self.path = path

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def append_data(self, frame):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.path))

    monkeypatch.setattr(imageio, "get_writer", FullDisk)
    recorder = _finalize(tmp_path, caplog)
    _check_not_written(recorder, tmp_path, caplog)


def test_a_video_cut_short_by_a_really_full_disk_is_not_logged_as_written(tmp_path, caplog):
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root (the ENOSPC test above runs everywhere)")
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(disk)],
                             capture_output=True)  # fmt: skip
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        recorder = _finalize(disk, caplog)
        _check_not_written(recorder, disk, caplog)
        assert "no moov box" in recorder.failed  # ffmpeg's trailer never made it to the disk
    finally:
        subprocess.run(["umount", str(disk)], check=True)


def test_a_ctrl_c_that_surfaces_as_a_librarys_error_still_ends_as_a_ctrl_c():
    """A KeyboardInterrupt raised inside a library whose ``finally`` then fails (OmegaConf's
    ``_invalidate_flags_cache`` on a half-built node, seen once at 0.5 s into start-up) reaches
    the entry point as a config error; ``reraise_if_interrupted`` turns it back into the Ctrl-C
    (exit 130), and leaves a config error that no Ctrl-C caused alone.

    Catches: a Ctrl-C at start-up ending as 'config error: ...' with exit 2."""
    from rlexp.config.validate import ConfigError
    from rlexp.runtime.outside_run import reraise_if_interrupted

    def library():
        try:
            raise KeyboardInterrupt
        finally:
            None._invalidate_flags_cache()  # type: ignore[attr-defined]

    try:
        try:
            library()
        except AttributeError as exc:
            raise ConfigError(str(exc)) from None
    except ConfigError as exc:
        with pytest.raises(KeyboardInterrupt):
            reraise_if_interrupted(exc)
    try:
        raise ConfigError("trainer.total_frames=-1: must be >= 1")
    except ConfigError as exc:
        reraise_if_interrupted(exc)  # nothing raised


# A C extension's module init that a Ctrl-C interrupts: pybind11 (MuJoCo's bindings) raises
# ``ImportError("initialization failed")`` from the KeyboardInterrupt (seen once at 2.0 s).
_EXTENSION_INIT = """
import sys
import rlexp.app
import rlexp.launch.precheck
from rlexp.runtime.entry import SignalInterrupt

def interrupted_import(*args, **kwargs):
    try:
        raise SignalInterrupt
    except KeyboardInterrupt as exc:
        raise ImportError("initialization failed") from exc

setattr({module}, {name!r}, interrupted_import)
from rlexp.cli import train
train(sys.argv[1:], prog="train.py")
"""


@pytest.mark.parametrize(
    "module, name", [("rlexp.launch.precheck", "precheck"), ("rlexp.app", "train")]
)
def test_a_ctrl_c_inside_a_c_extensions_import_ends_as_a_ctrl_c(tmp_path, children, module, name):
    """A Ctrl-C that lands inside MuJoCo's C-extension import, before the command-line check ends
    (``precheck``) or while the run is being built (``train``), reaches rlexp as an ``ImportError``
    chained to the interrupt: it ends as a Ctrl-C (one line, exit 130), no traceback, no status.

    Catches: 'ImportError: initialization failed' with a traceback and exit 1 (seen at 2.0 s)."""
    script = tmp_path / "interrupted_import.py"
    script.write_text(_EXTENSION_INIT.format(module=module, name=name))
    run_dir = tmp_path / "run"
    args = [*SHORT, "logger=none", f"hydra.run.dir={run_dir}"]
    proc = _launch(children, [sys.executable, str(script), *args], tmp_path)
    assert proc.returncode == 130, proc.stdout[-3000:] + proc.stderr[-3000:]
    both = proc.stdout + proc.stderr
    assert "Traceback" not in both and "initialization failed" not in both, both[-3000:]
    assert len([ln for ln in both.splitlines() if "interrupted" in ln]) == 1, both[-3000:]
    assert not (run_dir / "status.json").exists()


def test_the_entry_guard_ends_a_chained_ctrl_c_as_one_and_lets_other_errors_through(capsys):
    """``entry_guard``: an error chained (cause or context) to a KeyboardInterrupt is the Ctrl-C
    (one line, exit 130); the same error without one is a bug and keeps its traceback."""
    from rlexp.runtime.entry import SignalInterrupt, entry_guard

    def chained(by_cause: bool) -> None:
        try:
            raise SignalInterrupt
        except KeyboardInterrupt as exc:
            if by_cause:
                raise ImportError("initialization failed") from exc
            raise ImportError("initialization failed")  # noqa: B904 (the implicit context)

    for by_cause in (True, False):
        with pytest.raises(SystemExit) as ended, entry_guard("rlexp eval"):
            chained(by_cause)
        assert ended.value.code == 130
        err = capsys.readouterr().err
        assert err.strip().splitlines() == [
            "rlexp eval: interrupted (Ctrl-C) while no run was training: nothing to save"
        ], err
    with pytest.raises(ImportError, match="initialization failed"), entry_guard("rlexp eval"):
        raise ImportError("initialization failed")


def test_a_ctrl_c_that_a_library_replaces_with_an_unchained_error_still_ends_as_a_ctrl_c(capsys):
    """C code that clears the interrupt and raises its own error (``from None``: no chain to
    follow) after rlexp's start-up handler raised: the handler's record makes it the Ctrl-C it
    was (one line, exit 130). Without a Ctrl-C the same error keeps its traceback, and a new
    ``install`` (a new process state) forgets the record."""
    from rlexp.runtime import outside_run
    from rlexp.runtime.entry import entry_guard, note_sigint

    def library() -> None:
        try:
            signal.raise_signal(signal.SIGINT)  # rlexp's handler raises SignalInterrupt here
        except KeyboardInterrupt:
            raise RuntimeError("module init failed") from None

    saved = {s: signal.getsignal(s) for s in outside_run.STOP_SIGNALS}
    try:
        outside_run.install()
        with pytest.raises(RuntimeError), entry_guard("train.py"):
            raise RuntimeError("module init failed")  # no Ctrl-C yet: a bug, traceback kept
        with pytest.raises(SystemExit) as ended, entry_guard("train.py"):
            library()
        assert ended.value.code == 130
        assert capsys.readouterr().err.strip() == (
            "train.py: interrupted (Ctrl-C) while no run was training: nothing to save"
        )
        outside_run.install()
        with pytest.raises(RuntimeError), entry_guard("train.py"):
            raise RuntimeError("module init failed")
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)
        note_sigint(False)
