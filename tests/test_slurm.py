"""SLURM: the preemption handler and requeue decision (unit tests, default suite), and on a real
cluster (scripts/local-slurm.sh start) an array sweep and preemption: SIGUSR2 -> checkpoint at a
safe point -> requeue -> the same run dir resumes and finishes.

The cluster tests are marked ``slurm``: run them with ``make test-slurm`` (starts the local cluster
first); they are skipped when no cluster answers.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from conftest import REPO, Children


class FakeTrainer:
    def __init__(self) -> None:
        self.reasons: list[str] = []

    def request_stop(self, reason: str) -> None:
        self.reasons.append(reason)


@pytest.fixture
def usr2():
    """Restore this process's USR2 handler and the module's state after a test."""
    from rlexp.launch import slurm

    previous = signal.getsignal(signal.SIGUSR2)
    yield slurm
    signal.signal(signal.SIGUSR2, previous)
    slurm._state.__init__()


def test_no_handler_outside_slurm(usr2, monkeypatch):
    monkeypatch.delenv("SLURM_JOB_ID", raising=False)
    before = signal.getsignal(signal.SIGUSR2)
    assert usr2.install_preemption_handler(FakeTrainer()) is False
    assert signal.getsignal(signal.SIGUSR2) is before


def test_signal_only_requests_a_stop_and_remembers_submitits_handler(usr2, monkeypatch):
    monkeypatch.setenv("SLURM_JOB_ID", "42")
    calls = []
    signal.signal(signal.SIGUSR2, lambda *a: calls.append("submitit"))
    trainer = FakeTrainer()
    assert usr2.install_preemption_handler(trainer) is True
    os.kill(os.getpid(), signal.SIGUSR2)
    wait_for(lambda: trainer.reasons, 5, "the handler")
    # The stop is requested; submitit's handler (an immediate requeue) is not called.
    assert trainer.reasons == ["SLURM signal SIGUSR2 (job 42)"] and calls == []
    assert usr2.stop_requested_by_signal()


def test_launcher_requeues_only_jobs_stopped_by_the_signal(usr2, monkeypatch):
    from hydra.core.utils import JobReturn, JobStatus

    from rlexp.training.trainer import StopRequested

    class SignalHandler:  # stands in for submitit's, whose requeue ends with sys.exit
        def checkpoint_and_try_requeue(self, signum, frame):
            raise SystemExit(-1)

    SignalHandler.__module__ = "submitit.core.job_environment"

    def launcher_returning(status: JobStatus, value):
        class Base:
            def __call__(self):
                ret = JobReturn(status=status)
                ret._return_value = value
                return ret

        return type("L", (usr2.RequeueOnPreemption, Base), {})()

    usr2._state.previous = SignalHandler().checkpoint_and_try_requeue
    usr2._state.signum = int(signal.SIGUSR2)
    stopped = (JobStatus.FAILED, StopRequested("SLURM signal SIGUSR2"))
    # No signal: nothing to requeue.
    assert launcher_returning(*stopped)().status == JobStatus.FAILED
    usr2._state.requested = True
    assert launcher_returning(JobStatus.COMPLETED, 1.0)().return_value == 1.0  # finished anyway
    assert launcher_returning(JobStatus.FAILED, ValueError("x"))().status == JobStatus.FAILED
    with pytest.raises(SystemExit):
        launcher_returning(*stopped)()


#: One CPU and 1 GB per job so two jobs fit the 2-core CI node; timeout_min well above 10 so that
#: submitit counts a signal as a preemption, not a timeout (it deems a job "timed out" past
#: min(80%, limit - 10 min) of its time limit).
SLURM = [
    "hydra/launcher=slurm",
    "hydra.launcher.cpus_per_task=1",
    "hydra.launcher.mem_gb=1",
    "hydra.launcher.timeout_min=60",
]
TINY = [
    "env=inverted_pendulum",
    "trainer.frames_per_batch=256",
    "algorithm.num_epochs=1",
    "trainer.eval_episodes=2",
]


def _job_ids() -> set[str]:
    out = subprocess.run(["squeue", "-h", "-o", "%i"], capture_output=True, text=True).stdout
    return set(out.split())


@pytest.fixture(scope="module")
def cluster() -> Iterator[None]:
    if (
        shutil.which("sbatch") is None
        or subprocess.run(["sinfo"], capture_output=True).returncode != 0
    ):
        pytest.skip("no SLURM cluster answers: start one with `sudo scripts/local-slurm.sh start`")
    before = _job_ids()
    yield
    # A job can still be winding down (a rank's srun step) after the launcher has its result:
    # leave nothing of ours holding the node.
    left = sorted(_job_ids() - before)
    if left:
        subprocess.run(["scancel", *left], capture_output=True)


def env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO / "src"), "WANDB_MODE": "offline"}


def sweep(children: Children, args: list[str], cwd: Path) -> subprocess.Popen:
    """``python train.py -m ARGS`` in the background (the launcher blocks until all jobs finish);
    its process group is killed on the test's teardown (the jobs: ``cluster`` cancels them)."""
    return children.popen(
        [sys.executable, str(REPO / "train.py"), "-m", *args],
        cwd=cwd,
        env=env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def finish(proc: subprocess.Popen, timeout: float = 300) -> str:
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"sweep still running after {timeout} s:\n{out[-5000:]}") from None
    assert proc.returncode == 0, f"sweep exited {proc.returncode}:\n{out[-5000:]}"
    return out


def wait_for(predicate, timeout: float, what: str, interval: float = 0.25):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def scontrol_job(job_id: str) -> dict[str, str]:
    out = subprocess.run(["scontrol", "show", "job", job_id], capture_output=True, text=True).stdout
    return dict(re.findall(r"(\w+)=(\S*)", out))


@pytest.mark.slurm
def test_array_sweep_runs_every_job_as_an_array_task(cluster, tmp_path, children):
    sweep_dir = tmp_path / "sweep"
    out = finish(
        sweep(
            children,
            [
                *SLURM,
                "seed=0,1",
                *TINY,
                "trainer.total_frames=512",
                "trainer.eval_every=256",
                f"hydra.sweep.dir={sweep_dir}",
            ],
            tmp_path,
        )
    )
    assert "Submitit 'slurm' sweep output dir" in out
    for n in ("0", "1"):
        status = json.loads((sweep_dir / n / "status.json").read_text())
        assert status["state"] == "finished" and status["global_step"] == 512
    array_dirs = sorted(
        p.name for p in (sweep_dir / ".submitit").iterdir() if re.fullmatch(r"\d+_\d+", p.name)
    )
    assert len(array_dirs) == 2 and array_dirs[0].endswith("_0") and array_dirs[1].endswith("_1")
    script = next((sweep_dir / ".submitit").glob("*/*_submission.sh")).read_text()
    assert "#SBATCH --array=0-1%2" in script and "#SBATCH --signal=USR2@120" in script


@pytest.mark.slurm
def test_preempted_job_checkpoints_requeues_and_resumes_in_the_same_run_dir(
    cluster, tmp_path, children
):
    total = 32768  # 128 iterations: the signal lands mid-run
    proc = sweep(
        children,
        [
            *SLURM,
            "seed=0",
            *TINY,
            f"trainer.total_frames={total}",
            "trainer.eval_every=8192",
            "trainer.save_every=8192",
            "logger=[tensorboard,wandb]",
        ],
        tmp_path,
    )
    try:
        # The default sweep dir multirun/${now:...}/...: a restart must not re-resolve it.
        metrics = wait_for(
            lambda: next(iter(tmp_path.glob("multirun/*/*/0/metrics.jsonl")), None),
            120,
            "the job to start training",
        )
        run_dir = metrics.parent
        wait_for(lambda: metrics.read_text().count("perf/sps") >= 2, 60, "two training iterations")
        job_id = next(
            p.name
            for p in (run_dir.parent / ".submitit").iterdir()
            if re.fullmatch(r"\d+(_\d+)?", p.name)
        )
        # USR2 to the job's steps (what SLURM sends signal_delay_s before the time limit).
        subprocess.run(["scancel", "--signal=USR2", job_id], check=True)

        # The trainer stops at the end of its iteration with a checkpoint; the job requeues and
        # waits (BeginTime): release it now rather than after SLURM's ~2 minute requeue delay.
        stopped = wait_for(
            lambda: _status(run_dir).get("state") == "stopped" and _status(run_dir),
            60,
            "status 'stopped'",
        )
        wait_for(
            lambda: scontrol_job(job_id).get("JobState") == "PENDING", 60, "the job to be requeued"
        )
        # slurmd revokes the first attempt's credential when it ends and refuses a launch whose
        # credential was made in the same whole second ("Job N already killed, do not launch batch
        # job"; slurmctld: "Killing non-startable batch JobId=N: Job credential revoked"; seen 3
        # times in 13 runs). SLURM's own requeue delay (~2 min) always clears it; this early
        # release must come at least a second later.
        time.sleep(2)
        subprocess.run(["scontrol", "update", f"JobId={job_id}", "StartTime=now"], check=True)
        finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            subprocess.run(["scancel", job_id] if "job_id" in locals() else ["true"])

    stop_step = stopped["global_step"]
    assert 0 < stop_step < total and "SLURM signal SIGUSR2" in stopped["reason"]
    assert (
        run_dir / "checkpoints" / f"{OmegaConf.load(run_dir / 'config.yaml').trainer.exp_name}"
        f"_step_{stop_step:09d}.pt"
    ).exists()
    assert int(scontrol_job(job_id)["Restarts"]) >= 1
    log = "\n".join(p.read_text() for p in (run_dir.parent / ".submitit").glob("*/*_log.out"))
    assert re.search(r"SLURM job \d+ \(restart [1-9]\d*\)", log)  # SLURM_RESTART_COUNT >= 1
    assert "this job is preempted" in log and "Requeued job" in log
    assert "[resume] continuing from" in log and f"at step {stop_step}" in log

    status = _status(run_dir)
    assert status["state"] == "finished" and status["global_step"] == total
    # One run dir; training rows continue from the checkpoint: every iteration once, none from 0 again.
    assert [p for p in tmp_path.glob("multirun/*/*/*") if p.is_dir() and p.name != ".submitit"] == [
        run_dir
    ]
    steps = [
        json.loads(line)["step"] for line in metrics.read_text().splitlines() if "perf/sps" in line
    ]
    assert steps == list(range(256, total + 1, 256))
    # One W&B run id, reused by both attempts (two offline run dirs with the same id).
    run_id = (run_dir / "wandb_run_id.txt").read_text().strip()
    attempts = sorted((run_dir / "wandb").glob("offline-run-*"))
    assert len(attempts) == 2 and all(p.name.endswith(f"-{run_id}") for p in attempts)


def _status(run_dir: Path) -> dict:
    try:
        return json.loads((run_dir / "status.json").read_text())
    except (OSError, ValueError):
        return {}


@pytest.mark.slurm
def test_distributed_job_on_slurm_starts_its_ranks_as_tasks(cluster, tmp_path, children):
    """--distributed with tasks_per_node=2: one SLURM job, two ranks (submitit's environment),
    gradients averaged, one run dir."""
    sweep_dir = tmp_path / "sweep"
    proc = children.popen(  # its process group killed on teardown
        [
            sys.executable,
            str(REPO / "train.py"),
            "-m",
            "--distributed",
            *SLURM,
            "hydra.launcher.tasks_per_node=2",
            *TINY,
            "trainer.total_frames=1024",
            "trainer.eval_every=0",
            f"hydra.sweep.dir={sweep_dir}",
        ],
        cwd=tmp_path,
        env=env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    finish(proc)
    assert [p.name for p in sweep_dir.iterdir() if p.name.isdigit()] == ["0"]
    log = (sweep_dir / "0" / "train.log").read_text()
    assert "rank 0 of 2" in log and "rank 1 of 2" in log
    digests = re.findall(r"parameters identical on all 2 ranks \(sha256 (\w+)\)", log)
    assert len(digests) == 2 and digests[0] == digests[1]
    assert json.loads((sweep_dir / "0" / "status.json").read_text())["global_step"] == 1024
