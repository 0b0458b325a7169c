"""``env.backend=gymnasium_async`` workers (#43 item 10; docs/faults.md): a Ctrl-C that breaks the
build is a stop (130), not a config error; the number of worker processes is capped at the config
check; workers end when the training process is gone, even stuck in an env step; what user code
raises in a worker (numpy's MemoryError, ``sys.exit``) reaches the user as one clear line."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import psutil
import pytest
from fault_envs import tiny_run

from conftest import REPO, Children, compose, run_train
from rlexp.config.validate import ConfigError, to_root_config

TESTS = Path(__file__).resolve().parent
PYPATH = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}"}  # fault_envs, stuck_envs
FAULT_ENVS = str(TESTS / "fault_envs.py")

RUN = tiny_run()


def test_the_worker_processes_of_gymnasium_async_are_capped_at_the_config_check():
    cap = max(64, 4 * len(os.sched_getaffinity(0)))
    base = ["env=hopper", "env.backend=gymnasium_async", "trainer.frames_per_batch=65536"]
    with pytest.raises(ConfigError) as err:
        to_root_config(compose([*base, "env.num_envs=65536"]))
    assert str(err.value) == (
        f"env.num_envs=65536 with env.backend=gymnasium_async would start 65536 worker "
        f"processes (one per copy); the cap here is {cap} (4 per CPU, at least 64): use "
        f"env.num_envs<={cap}, or env.backend=gymnasium (every copy in the training process)"
    )
    with pytest.raises(ConfigError, match=rf"env.num_eval_envs={cap + 1} .*cap here is {cap}"):
        to_root_config(compose([*base, "env.num_envs=1", f"env.num_eval_envs={cap + 1}"]))
    to_root_config(compose([*base, f"env.num_envs={cap}", "trainer.frames_per_batch=" + str(cap)]))
    # the in-process backend has no worker processes: no such cap
    to_root_config(compose(["env=hopper", "env.num_envs=128", "trainer.frames_per_batch=128"]))


def test_a_ctrl_c_that_breaks_the_build_is_a_stop_130_not_a_config_error(tmp_path):
    marker = tmp_path / "built_once"
    proc = run_train(
        [*RUN, f"+env.kwargs.interrupt_marker={marker}", f"hydra.run.dir={tmp_path / 'run'}"],
        cwd=tmp_path, check=False, env_extra=PYPATH, timeout=300,
    )  # fmt: skip
    out = proc.stdout + proc.stderr
    assert proc.returncode == 128 + signal.SIGINT, out[-3000:]
    assert "interrupted (SIGINT received) while the run was built: nothing trained" in out
    assert "config error" not in out and "Traceback" not in out, out[-3000:]
    assert not (tmp_path / "run" / "status.json").exists()


@pytest.mark.parametrize(
    ("what", "shown"),
    [("memory", "MemoryError: Unable to allocate 2.00 PiB"), ("exit0", "SystemExit(0)")],
)
def test_what_user_code_raises_in_a_worker_is_one_clear_line(tmp_path, what, shown):
    run_dir = tmp_path / "run"
    proc = run_train(
        [*RUN, "env.backend=gymnasium_async", "env.num_envs=2", "+env.kwargs.exit_at=100",
         f"+env.kwargs.raise_what={what}", f"hydra.run.dir={run_dir}"],
        cwd=tmp_path, check=False, env_extra=PYPATH, timeout=300,
    )  # fmt: skip
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out[-3000:]
    reason = json.loads((run_dir / "status.json").read_text())["reason"]
    assert f"(env.backend=gymnasium_async): a worker failed: {shown}" in reason, reason
    assert f"(raised in _raise() at {FAULT_ENVS}:" in reason
    assert "TypeError" not in reason


@pytest.mark.parametrize(
    ("what", "shown"),
    [("memory", "MemoryError: Unable to allocate 2.00 PiB"), ("exit0", "SystemExit(0)")],
)
def test_what_user_code_raises_while_a_reseeded_copy_is_made_anew_is_one_clear_line(
    monkeypatch, what, shown
):
    """A reseed after use makes each copy anew (``rlexp_remake``: the old one closed, a new one
    made): what the env's ``close`` raises there is one line, as in ``step``, not a garbled
    ``TypeError`` or a worker that ``SystemExit`` ended; every worker is closed."""
    from rlexp.envs.gym_async import AsyncGymnasiumEnv, WorkerError

    monkeypatch.setenv("PYTHONPATH", PYPATH["PYTHONPATH"])
    env = AsyncGymnasiumEnv(
        "fault_envs:Walk-v0", 2, make_kwargs={"exit_in": "close", "exit_at": 1, "raise_what": what}
    )
    try:
        env.set_seed(3)
        env.reset()
        with pytest.raises(WorkerError) as err:
            env.set_seed(3)  # an eval round's reseed: the copies are made anew
        msg = str(err.value)
        assert "\n" not in msg and msg.startswith(
            f"env.name='fault_envs:Walk-v0' (env.backend=gymnasium_async): a worker failed: {shown}"
        ), msg
        assert f"(raised in _raise() at {FAULT_ENVS}:" in msg and "TypeError" not in msg, msg
        assert msg.endswith("; all workers are closed"), msg
        assert not any(p.is_alive() for p in env._vec.processes)
    finally:
        env.close()


def test_a_run_whose_env_exits_in_close_at_an_eval_reseed_fails_in_one_line_exit_1(tmp_path):
    """The eval env is reseeded every round: the second round makes its copies anew, the old
    copy's ``close`` calls ``sys.exit(0)``: docs/faults.md's worker error, exit 1, ``failed``."""
    run_dir = tmp_path / "run"
    proc = run_train(
        [*RUN, "env.backend=gymnasium_async", "trainer.eval_every=128", "trainer.eval_episodes=1",
         "trainer.eval_async=false", "+env.kwargs.exit_in=close", "+env.kwargs.exit_at=1",
         f"hydra.run.dir={run_dir}"],
        cwd=tmp_path, check=False, env_extra=PYPATH, timeout=300,
    )  # fmt: skip
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out[-3000:]
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "failed" and status["global_step"] == 256, status
    assert status["reason"].startswith(
        "WorkerError: env.name='fault_envs:Walk-v0' (env.backend=gymnasium_async): a worker "
        f"failed: SystemExit(0) (raised in _raise() at {FAULT_ENVS}:"
    ), status["reason"]
    assert "\n" not in status["reason"]


def test_workers_stuck_in_a_step_end_when_the_training_process_group_is_killed(tmp_path):
    args = ["env=hopper", "env.name=stuck_envs:StuckAfter-v0", "+env.kwargs.after=300",
            "env.backend=gymnasium_async", "env.num_envs=2", "trainer.frames_per_batch=256",
            "trainer.eval_every=0", "trainer.total_frames=100000", "algorithm.num_epochs=1",
            "trainer.progress=false", "logger=none", f"hydra.run.dir={tmp_path / 'run'}"]  # fmt: skip
    log = tmp_path / "run" / "train.log"
    with Children() as children:
        proc = children.train(args, tmp_path, tmp_path / "run.txt", env_extra=PYPATH)
        deadline, workers = time.time() + 180, []
        while time.time() < deadline and proc.poll() is None:
            if log.exists() and "[train] step=256" in log.read_text():
                workers = [p.pid for p in psutil.Process(proc.pid).children(recursive=True)]
                break
            time.sleep(0.05)
        assert workers, (tmp_path / "run.txt").read_text()[-3000:]
        time.sleep(1.0)  # the workers' second rollout: stuck in step 301 for good
        os.killpg(proc.pid, signal.SIGKILL)  # the whole group: the forkserver too, not the workers
        proc.wait(timeout=30)
        deadline = time.time() + 20
        while time.time() < deadline and not all(_gone(p) for p in workers):
            time.sleep(0.05)
        left = [p for p in workers if not _gone(p)]
        for pid in left:  # end them here: the test must leave nothing behind
            os.kill(pid, signal.SIGKILL)
        assert not left, "gymnasium_async workers outlived the training process"


def _gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True
