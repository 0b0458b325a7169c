"""A run whose loop stops making progress (#29, item 4): the heartbeat records the step and when it
last moved, ``rlexp runs`` shows ``stalled`` past the run's own ``trainer.stall_timeout_s``; the
waits on the eval worker and on other ranks are bounded by it and end the run with one line; a stop
signal ends a run stuck in user code within ``trainer.stop_grace_s`` (128 + N, ``interrupted``)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from conftest import REPO, _live_descendants
from rlexp.analysis import runs
from rlexp.analysis.liveness import Here, liveness
from rlexp.run.rundir import Heartbeat, read_heartbeat
from rlexp.training.eval_worker import EvalRound, EvalSetup, EvalWorker

TESTS = Path(__file__).resolve().parent
HERE = Here(socket.gethostname(), None, None, 100)
ENV = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}", "MUJOCO_GL": "egl"}


def _beat(**kw) -> dict:
    """A heartbeat from another host, written now (fresh), whose step last moved ``kw`` ago."""
    return {"host": "node-7", "pid": 4242, "interval_s": 10.0, "time": 10_000.0, **kw}


# -- the rule --------------------------------------------------------------------------------------
def test_a_fresh_heartbeat_whose_step_has_not_moved_past_the_runs_own_bound_is_stalled():
    running = {"state": "running", "pid": 4242}
    # 12 minutes without a step, this run's bound 10 minutes: stalled, with the run's numbers.
    beat = _beat(global_step=4096, step_time=10_000.0 - 720, stall_timeout_s=600.0)
    assert liveness(running, beat, 10_005.0, HERE) == (
        "stalled",
        "step 4096 has not moved for 12m05s (stalled after 10m00s), on host node-7",
    )
    # The same 12 minutes under a bound of 20 minutes (a run with long eval rounds): running.
    beat["stall_timeout_s"] = 1200.0
    assert liveness(running, beat, 10_005.0, HERE) == ("running", "")
    # A heartbeat from before step_time was recorded: nothing to tell from, running.
    assert liveness(running, _beat(global_step=1), 10_005.0, HERE) == ("running", "")


def test_a_live_process_on_this_host_whose_loop_is_stuck_is_stalled_not_running(tmp_path):
    me = {"host": socket.gethostname(), "pid": os.getpid()}
    beat = {**_beat(**me), "time": time.time(), "step_time": time.time() - 95, "global_step": 768,
            "stall_timeout_s": 30.0}  # fmt: skip
    (tmp_path / "heartbeat.json").write_text(json.dumps(beat))
    (tmp_path / "status.json").write_text(
        json.dumps({"state": "running", "pid": os.getpid(), **me})
    )
    row = runs.read_run(tmp_path)
    assert row.status == "stalled" and row.resume is None
    assert re.fullmatch(
        rf"PID {os.getpid()} is alive but step 768 has not moved for 1m3[5-9]s \(stalled after 30s\)",
        row.note,
    ), row.note


def test_the_heartbeat_records_when_the_step_last_moved_and_beats_when_the_bound_is_crossed(
    tmp_path, monkeypatch
):
    monkeypatch.setattr("rlexp.run.rundir.STEP_POLL_S", 0.05)
    step = {"n": 0}
    beat = Heartbeat(tmp_path, lambda: {"global_step": step["n"]}, 3600.0, stall_timeout_s=0.3)
    beat.start()  # writes now, then only every hour: what comes next is the stall's own beat
    try:
        first = read_heartbeat(tmp_path)
        assert first["stall_timeout_s"] == 0.3 and first["step_time"] <= first["time"]
        deadline = time.time() + 20
        while time.time() < deadline and read_heartbeat(tmp_path)["time"] == first["time"]:
            time.sleep(0.02)
        stalled = read_heartbeat(tmp_path)
        assert stalled["time"] - stalled["step_time"] > 0.3  # the stall beat, long before the hour
        assert stalled["step_time"] == first["step_time"] and stalled["global_step"] == 0
        step["n"] = 256
        time.sleep(0.3)
    finally:
        beat.stop()
    last = read_heartbeat(tmp_path)
    assert last["global_step"] == 256 and last["step_time"] > stalled["step_time"]


# -- the eval worker's round -----------------------------------------------------------------------
class _Alive:
    pid = 4242
    exitcode = None

    def is_alive(self) -> bool:
        return True


class _SilentPipe:
    """A pipe on which nothing ever arrives; each ``poll(t)`` moves the fake clock on by ``t``
    (instead of waiting), so the bound is checked on the clock the worker reads, not on how fast
    this machine runs."""

    def __init__(self) -> None:
        self.now = 1000.0
        self.polls: list[float] = []

    def poll(self, timeout: float) -> bool:
        self.polls.append(timeout)
        self.now += timeout
        return False


def test_an_eval_worker_that_never_answers_fails_within_the_bound_naming_it(monkeypatch):
    import types

    import rlexp.training.eval_worker as eval_worker

    pipe = _SilentPipe()
    monkeypatch.setattr(eval_worker, "time", types.SimpleNamespace(monotonic=lambda: pipe.now))
    worker = EvalWorker(EvalSetup(None, None, 0, 1), timeout_s=0.5, _proc=_Alive(), _conn=pipe)
    worker._ready = True
    worker.in_flight = EvalRound(1536, {})
    with pytest.raises(RuntimeError) as err:
        worker.result()
    # Given up at the first 0.1 s poll that ends 0.5 s of silence (up to float rounding).
    assert set(pipe.polls) == {0.1} and 0.5 - 1e-9 < pipe.now - 1000.0 <= 0.6 + 1e-9
    assert str(err.value) == (
        "the eval worker (pid 4242) did not answer for its eval round of step 1536 within "
        "trainer.stall_timeout_s=0.5 s (stopped, or stuck in the eval env); "
        "trainer.eval_async=false evaluates in this process"
    )
    assert worker.in_flight is not None  # still in flight: the checkpoint records it for a resume
    # Its start-up (spawn, imports, its env) gets at least STARTUP_TIMEOUT_MIN_S, said so.
    monkeypatch.setattr("rlexp.training.eval_worker.STARTUP_TIMEOUT_MIN_S", 1.5)
    pipe.polls.clear()
    start = pipe.now
    with pytest.raises(RuntimeError, match=re.escape(
        "did not answer for its start-up within 1.5 s (trainer.stall_timeout_s=0.5 s, at least "
        "1.5 s to start)")):  # fmt: skip
        worker._receive("ready", "start-up")
    assert set(pipe.polls) == {0.1} and 1.5 - 1e-9 < pipe.now - start <= 1.6 + 1e-9


def test_a_stopped_eval_worker_ends_the_run_with_a_checkpoint_and_one_line(tmp_path, children):
    """SIGSTOP the eval worker of a real run: the next wait for its round fails after
    trainer.stall_timeout_s, exit 1, status failed naming the worker, the update saved."""
    run_dir = tmp_path / "run"
    args = ["env=inverted_pendulum", "trainer.total_frames=200000", "trainer.frames_per_batch=256",
            "trainer.eval_every=256", "trainer.eval_episodes=2", "trainer.save_every=100000",
            "trainer.eval_async=true", "algorithm.num_epochs=1", "trainer.progress=false",
            "trainer.stall_timeout_s=8", f"hydra.run.dir={run_dir}"]  # fmt: skip
    console = tmp_path / "console.txt"
    proc = children.train(args, tmp_path, console, env_extra=ENV)
    worker, deadline = None, time.time() + 300
    while time.time() < deadline and proc.poll() is None and worker is None:
        found = re.search(r"\[eval\] step=\d+", console.read_text())  # a round came back
        pid = re.search(r"eval worker started \(pid (\d+)\)", console.read_text())
        worker = int(pid.group(1)) if found and pid else None
        time.sleep(0.05)
    assert worker is not None, console.read_text()[-3000:]
    os.kill(worker, signal.SIGSTOP)
    stopped = time.monotonic()
    proc.wait(timeout=120)
    took = time.monotonic() - stopped
    out = console.read_text()
    assert proc.returncode == 1, out[-3000:]
    # Not before the bound (the upper end is the unit test's, on a fake clock: no wall-clock
    # bound here; a wait far past it ends at proc.wait's 120 s and fails)
    assert took >= 8, took
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "failed"
    assert (
        f"the eval worker (pid {worker}) did not answer for its eval round of step"
        in status["reason"]
    )
    assert "within trainer.stall_timeout_s=8 s" in status["reason"]
    saved = sorted(run_dir.glob("checkpoints/*_step_*.pt"))
    assert saved and f"the last good checkpoint is {saved[-1]}" in status["reason"]
    assert "Traceback" not in out
    assert [ln for ln in out.splitlines() if "ERROR" in ln] == [
        ln for ln in out.splitlines() if "ERROR" in ln and "did not answer" in ln
    ]


# -- a loop stuck in user code ---------------------------------------------------------------------
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_run_stuck_in_an_env_step_is_stalled_and_a_stop_signal_still_ends_it(
    sig, tmp_path, children
):
    """stuck_envs:StuckAfter-v0 hangs in step 301 (after the checkpoint of step 256): `rlexp runs`
    shows the run stalled, and the stop signal ends it within trainer.stop_grace_s: 128 + N,
    interrupted, the reason naming the checkpoint a resume continues from."""
    run_dir = tmp_path / "stuck"
    args = ["env=hopper", "env.name=stuck_envs:StuckAfter-v0", "+env.kwargs.after=300",
            "env.num_envs=1", "trainer.frames_per_batch=256", "trainer.save_every=256",
            "trainer.eval_every=0", "trainer.total_frames=100000", "algorithm.num_epochs=1",
            "trainer.progress=false", "trainer.stall_timeout_s=2", "trainer.stop_grace_s=4",
            f"hydra.run.dir={run_dir}"]  # fmt: skip
    console = tmp_path / "console.txt"
    proc = children.train(args, tmp_path, console, env_extra=ENV)
    deadline = time.time() + 150
    while time.time() < deadline and proc.poll() is None:
        if runs.read_run(run_dir).status == "stalled":
            break
        time.sleep(0.2)
    listed = subprocess.run([sys.executable, "-m", "rlexp", "runs", "--json", str(tmp_path)],
                            capture_output=True, text=True, timeout=120,
                            env={**os.environ, **ENV})  # fmt: skip
    (row,) = json.loads(listed.stdout)
    assert row["status"] == "stalled", (row, console.read_text()[-3000:])
    assert re.fullmatch(
        rf"PID {proc.pid} is alive but step 256 has not moved for \d+s \(stalled after 2s\)",
        row["note"],
    ), row["note"]
    ckpt = run_dir / "checkpoints" / "stuck_envs-StuckAfter-v0_ppo_step_000000256.pt"
    assert ckpt.is_file()

    proc.send_signal(sig)
    sent = time.monotonic()
    proc.wait(timeout=120)
    took = time.monotonic() - sent
    out = console.read_text()
    assert proc.returncode == 128 + sig, out[-3000:]
    assert took >= 4, took  # not before the grace (its length: test_the_stop_watchdog_waits_...)
    status = json.loads((run_dir / "status.json").read_text())
    assert (status["state"], status["global_step"]) == ("interrupted", 256)
    assert status["reason"] == (
        f"{signal.Signals(sig).name} received at step 256: the loop did not reach its safe point "
        "within trainer.stop_grace_s=4 s (stuck in an env step or other user code?), so no "
        f"checkpoint was possible at the safe point; the resume point is {ckpt}"
    )
    assert sorted(p.name for p in run_dir.glob("checkpoints/*.pt")) == [ckpt.name]
    assert "Traceback" not in out
    assert runs.read_run(run_dir).status == "interrupted"


def test_the_stop_watchdog_waits_exactly_the_grace_then_expires(tmp_path, monkeypatch):
    """The countdown's length, recorded rather than timed: the watchdog waits ``stop_grace_s`` on
    its cancel event, then expires with the signal; disarmed in time, it does not."""
    from rlexp.run.stalls import StopWatchdog

    trainer = SimpleNamespace(last_checkpoint=None, global_step=0, last_eval={})
    dog = StopWatchdog(trainer, tmp_path, None, grace_s=4.5)
    waits, expired = [], []
    monkeypatch.setattr(dog._cancel, "wait", lambda t: waits.append(t) or False)  # timed out
    monkeypatch.setattr(dog, "expire", expired.append)
    dog._wait(signal.SIGTERM)
    assert waits == [4.5] and expired == [signal.SIGTERM]
    monkeypatch.setattr(dog._cancel, "wait", lambda t: waits.append(t) or True)  # disarmed
    dog._wait(signal.SIGINT)
    assert waits == [4.5, 4.5] and expired == [signal.SIGTERM]


def test_set_timeout_hands_the_configs_bound_to_the_process_group(monkeypatch):
    """``trainer.stall_timeout_s`` becomes the process group's collective timeout (recorded, not
    timed; the two-rank tests below show gloo keeping to it)."""
    from datetime import timedelta

    import torch.distributed as dist

    from rlexp.runtime import distributed

    given = []
    monkeypatch.setattr(distributed, "_INFO", SimpleNamespace(enabled=True, rank=0))
    monkeypatch.setattr(distributed, "_TIMEOUT_S", 120.0)
    monkeypatch.setattr(dist, "is_initialized", lambda: True)
    monkeypatch.setattr(dist.distributed_c10d, "_set_pg_timeout", given.append, raising=False)
    distributed.set_timeout(2.5)
    assert given == [timedelta(seconds=2.5)] and distributed._TIMEOUT_S == 2.5


# -- collectives -----------------------------------------------------------------------------------
_RANK = """
import os, sys, time, torch
from rlexp.runtime import distributed
distributed._join("test", 600.0)  # an all-reduce left at this bound outlasts the test's 120 s
distributed.set_timeout(2.0)
if distributed.info().rank == 1:
    time.sleep(120)  # a rank that stopped
start = time.monotonic()
try:
    distributed.all_reduce_sum(torch.ones(1))
except distributed.CollectiveTimeout as exc:
    print(f"{time.monotonic() - start:.1f}|{exc}", flush=True)
    os._exit(7)  # gloo's threads can abort an interpreter's teardown (rlexp.app._exit)
"""


def test_a_rank_that_stops_makes_the_other_fail_with_one_line_within_the_configs_bound(
    tmp_path, children
):
    """gloo's own bound is 30 minutes, and the one given at init here is 600 s: the config's
    bound (set_timeout, 2 s) is the one an all-reduce waits (one left at the init's would outlast
    the 120 s this test waits, and fail it; no wall-clock bound is asserted)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    procs = []
    for rank in (0, 1):
        env = {**os.environ, **ENV, "RANK": str(rank), "LOCAL_RANK": str(rank), "WORLD_SIZE": "2",
               "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "OMP_NUM_THREADS": "1"}  # fmt: skip
        out = open(tmp_path / f"rank{rank}.txt", "w")
        procs.append(children.popen([sys.executable, "-c", _RANK], env=env, stdout=out,
                                    stderr=subprocess.STDOUT))  # fmt: skip
    procs[0].wait(timeout=120)
    text = (tmp_path / "rank0.txt").read_text()
    assert procs[0].returncode == 7, text[-3000:]
    waited, message = text.strip().splitlines()[-1].split("|")
    assert float(waited) >= 2.0, waited  # (the init's 600 s would end at the 120 s wait: a failure)
    assert message == (
        "rank 0: an all-reduce waited more than trainer.stall_timeout_s=2 s for the other ranks "
        "(one of them stopped, or is stuck in its env or an eval round)"
    )


def test_a_stopped_rank_ends_a_two_rank_run_with_one_line_within_the_bound(tmp_path, children):
    """torchrun, 2 ranks: SIGSTOP rank 1 after a checkpoint; rank 0 fails in its next collective
    after trainer.stall_timeout_s (not gloo's 30 minutes): status failed, one line naming the
    bound, the last good checkpoint kept; torchrun ends the job."""
    run_dir = tmp_path / "run"
    args = ["env=inverted_pendulum", "trainer.frames_per_batch=256", "algorithm.num_epochs=1",
            "trainer.eval_every=0", "trainer.save_every=512", "trainer.total_frames=10000000",
            "trainer.progress=false", "trainer.stall_timeout_s=10", f"hydra.run.dir={run_dir}"]  # fmt: skip
    env = {**os.environ, **ENV, "OMP_NUM_THREADS": "1"}
    with open(tmp_path / "console.txt", "w") as out:
        proc = children.popen(
            [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
             str(REPO / "train.py"), "--distributed", *args],
            cwd=tmp_path, env=env, stdout=out, stderr=subprocess.STDOUT,
        )  # fmt: skip
    rank1, ranks, deadline = None, [], time.time() + 300
    try:
        while time.time() < deadline and proc.poll() is None and rank1 is None:
            if list(run_dir.glob("checkpoints/*_step_*.pt")):
                rank0 = read_heartbeat(run_dir)["pid"]
                ranks = [p for p, argv in _live_descendants(proc.pid).items() if "-u" in argv[1:2]]
                (rank1,) = set(ranks) - {rank0}
                os.kill(rank1, signal.SIGSTOP)
            time.sleep(0.02)
        assert rank1 is not None, (tmp_path / "console.txt").read_text()[-3000:]
        stopped = time.monotonic()
        while time.monotonic() - stopped < 120:
            if json.loads((run_dir / "status.json").read_text())["state"] != "running":
                break
            time.sleep(0.1)
        took = time.monotonic() - stopped
        os.kill(rank1, signal.SIGKILL)  # torchrun would wait 30 s for a stopped rank to end
        proc.wait(timeout=120)
    finally:  # torchrun starts each rank in a session of its own: the fixture would miss them
        for pid in ranks:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "failed", status
    assert took >= 10, took  # (and ended within the 120 s polled above: status says failed)
    assert "waited more than trainer.stall_timeout_s=10 s for the other ranks" in status["reason"]
    saved = sorted(run_dir.glob("checkpoints/*_step_*.pt"))
    assert f"the last good checkpoint is {saved[-1]}" in status["reason"]
    errors = [ln for ln in (run_dir / "train.log").read_text().splitlines() if "ERROR" in ln]
    assert len(errors) == 1 and "waited more than" in errors[0], errors
