"""One job of a local sweep that dies (SIGKILL, as the OOM killer sends) never takes its siblings
down (#43 item 4; rlexp.launch.job_pool, docs/faults.md): the dead job is recorded ``failed`` with
how it died and its resume point, the others run to their end, a job not yet started starts, the
sweep prints its summary line and exits 1 without a traceback, and the same command again resumes
the dead job from its checkpoint."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

from fault_envs import tiny_run

from conftest import REPO, run_train

TESTS = Path(__file__).resolve().parent
PYPATH = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}"}  # fault_envs importable

JOB = tiny_run("trainer.total_frames=768")


def _status(job: Path) -> dict:
    return json.loads((job / "status.json").read_text())


def _steps(job: Path) -> list[int]:
    rows = [json.loads(x) for x in (job / "metrics.jsonl").read_text().splitlines()]
    return [r["step"] for r in rows if "perf/sps" in r]


def test_a_sigkilled_job_is_recorded_and_its_siblings_and_later_jobs_run_to_their_end(tmp_path):
    sweep, marker = tmp_path / "sweep", tmp_path / "killed"
    command = [
        "-m",
        "hydra/launcher=local",
        "hydra.launcher.n_jobs=2",
        *JOB,
        # job 1 SIGKILLs its own process at its 300th env step (once: the marker file)
        "+env.kwargs.kill_at=0,300,0",
        f"+env.kwargs.marker={marker}",
        f"hydra.sweep.dir={sweep}",
    ]
    proc = run_train(command, cwd=tmp_path, check=False, env_extra=PYPATH, timeout=400)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out[-4000:]
    assert "Traceback" not in out and "TerminatedWorkerError" not in out, out[-4000:]
    assert marker.exists()
    for n in ("0", "2"):  # the sibling and the job after it: finished, every step once
        assert _status(sweep / n)["state"] == "finished", out[-4000:]
        assert _steps(sweep / n) == list(range(128, 769, 128))
    dead = _status(sweep / "1")
    assert dead["state"] == "failed" and dead["exit_code"] == 128 + signal.SIGKILL
    assert "was killed by SIGKILL" in dead["reason"]
    assert "after step 256" in dead["reason"]  # its last checkpoint (300 env steps, 128 a batch)
    assert "fault_envs-Walk-v0_ppo_step_000000256.pt" in dead["reason"]
    assert f"sweep {sweep}: 2 of 3 jobs finished; 1 failed: {sweep / '1'}" in out

    # The same command again: the finished jobs are skipped, the dead one resumes from step 256.
    again = run_train(command, cwd=tmp_path, check=False, env_extra=PYPATH, timeout=400)
    out = again.stdout + again.stderr
    assert again.returncode == 0, out[-4000:]
    assert f"sweep {sweep}: 3 of 3 jobs finished" in out
    assert _status(sweep / "1")["state"] == "finished"
    assert _steps(sweep / "1") == list(range(128, 769, 128))  # one run: 384.. after 256
    assert "at step 256" in (sweep / "1" / "train.log").read_text()
