"""Local sweeps: a grid multirun, its report, a re-run that skips finished jobs and resumes the others,
Optuna, the parallel (joblib) launcher, and every sweep/launcher config in conf/."""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
from test_slurm import SLURM, cluster  # noqa: F401 (the fixture: a cluster that answers)

from conftest import CONF_DIR, REPO, SWEEP_TINY, run_train

GRID = ["seed=0,1", "algorithm.clip_epsilon=0.1,0.2"]


def grid_command(sweep_dir: Path) -> list[str]:
    return ["-m", *GRID, *SWEEP_TINY, f"hydra.sweep.dir={sweep_dir}"]


def rows(job: Path) -> list[dict]:
    return [json.loads(line) for line in (job / "metrics.jsonl").read_text().splitlines()]


def final_eval(job: Path) -> float:
    """The last eval/episode_return in a job's metrics.jsonl, read independently of rlexp.analysis.report."""
    return [r["eval/episode_return"] for r in rows(job) if "eval/episode_return" in r][-1]


def fingerprint(directory: Path) -> dict[str, tuple[int, int, str]]:
    return {
        p.name: (p.stat().st_size, p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
        for p in sorted(directory.iterdir())
        if p.is_file()
    }


@pytest.fixture(scope="module")
def grid_sweep(tmp_path_factory) -> Path:
    """``python train.py -m seed=0,1 algorithm.clip_epsilon=0.1,0.2`` on tiny budgets (4 jobs)."""
    root = tmp_path_factory.mktemp("grid")
    sweep = root / "sweep"
    run_train(grid_command(sweep), cwd=root)
    return sweep


def test_grid_multirun_writes_one_finished_job_dir_per_combination(grid_sweep):
    jobs = sorted(p for p in grid_sweep.iterdir() if p.is_dir())
    assert [p.name for p in jobs] == ["0", "1", "2", "3"]
    combos = set()
    for job in jobs:
        status = json.loads((job / "status.json").read_text())
        assert status["state"] == "finished" and status["global_step"] == 512
        overrides = OmegaConf.to_container(OmegaConf.load(job / ".hydra/overrides.yaml"))
        combos.add(
            tuple(o for o in overrides if o.startswith(("seed=", "algorithm.clip_epsilon=")))
        )
        config = OmegaConf.load(job / "config.yaml")
        assert f"seed={config.seed}" in overrides
        assert f"algorithm.clip_epsilon={config.algorithm.clip_epsilon}" in overrides
    assert len(combos) == 4


def test_report_numbers_match_the_jsonl_files(grid_sweep):
    proc = subprocess.run(
        [sys.executable, "-m", "rlexp.cli", "report", str(grid_sweep)],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(REPO / "src")},
    )
    assert proc.returncode == 0, proc.stderr
    for name in ("report.md", "report.csv", "curves.png"):
        assert (grid_sweep / name).stat().st_size > 0, name
    assert (grid_sweep / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (
        "algorithm.clip_epsilon=0.1" in proc.stdout
        and "Unfinished or failed jobs (0)" in proc.stdout
    )

    # The expected numbers, from the JSONL files and overrides alone.
    expected: dict[str, list[float]] = {}
    for job in sorted(p for p in grid_sweep.iterdir() if p.is_dir()):
        overrides = OmegaConf.to_container(OmegaConf.load(job / ".hydra/overrides.yaml"))
        clip = next(o for o in overrides if o.startswith("algorithm.clip_epsilon="))
        expected.setdefault(clip, []).append(final_eval(job))
    with open(grid_sweep / "report.csv") as f:
        table = {r["configuration"]: r for r in csv.DictReader(f)}
    assert set(table) == set(expected)
    for clip, finals in expected.items():
        r, x = table[clip], np.array(finals)
        assert int(r["n_seeds"]) == 2 and r["seeds"] == "0 1"
        assert float(r["final_mean"]) == pytest.approx(x.mean())
        assert float(r["final_std"]) == pytest.approx(x.std(ddof=1))
        assert float(r["iqm"]) == pytest.approx(x.mean())  # with two seeds the IQM is the mean
        assert x.min() - 1e-9 <= float(r["iqm_ci_low"]) <= float(r["iqm_ci_high"]) <= x.max() + 1e-9
        assert float(r["steps"]) == 512 and float(r["time_s"]) > 0
        assert int(r["n_unfinished"]) == 0


def test_rerun_skips_finished_jobs_and_resumes_unfinished_ones(grid_sweep, tmp_path):
    sweep = tmp_path / "sweep"
    shutil.copytree(grid_sweep, sweep)
    # Job 1 "was preempted" after its step-256 checkpoint: later checkpoint and rows gone, status stopped.
    job1 = sweep / "1"
    for ckpt in (job1 / "checkpoints").glob("*_step_*.pt"):
        if not ckpt.name.endswith("_step_000000256.pt"):
            ckpt.unlink()
    (job1 / "metrics.jsonl").write_text(
        "".join(json.dumps(r) + "\n" for r in rows(job1) if r["step"] <= 256)
    )
    status = json.loads((job1 / "status.json").read_text())
    (job1 / "status.json").write_text(
        json.dumps({**status, "state": "stopped", "global_step": 256})
    )
    before = {n: fingerprint(sweep / n / "checkpoints") for n in ("0", "2", "3")}
    metrics_before = {n: (sweep / n / "metrics.jsonl").read_bytes() for n in ("0", "2", "3")}

    proc = run_train(grid_command(sweep), cwd=tmp_path)
    out = proc.stdout + proc.stderr

    for n in ("0", "2", "3"):
        assert f"run dir {sweep / n} already finished at step 512: skipping" in out
        assert fingerprint(sweep / n / "checkpoints") == before[n]  # nothing trained or saved
        assert (sweep / n / "metrics.jsonl").read_bytes() == metrics_before[n]
    assert f"run dir {job1} already finished" not in out
    # "[resume] continuing from ..._step_000000256.pt at step 256"
    assert "at step 256" in (job1 / "train.log").read_text()
    status = json.loads((job1 / "status.json").read_text())
    assert status["state"] == "finished" and status["global_step"] == 512
    train_steps = [r["step"] for r in rows(job1) if "perf/sps" in r]
    assert train_steps == [256, 512]  # continued from 256, not from 0
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1", "2", "3"]


def test_report_lists_unfinished_failed_and_missing_jobs(tmp_path):
    """Synthetic sweep: 4 finished seeds (IQM by hand), a failed job, a job without status.json."""
    from rlexp.analysis.report import report

    def job(
        num: int, overrides: list[str], state: str | None, evals: list[tuple[int, float]]
    ) -> None:
        d = tmp_path / str(num)
        (d / ".hydra").mkdir(parents=True)
        (d / ".hydra/overrides.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(overrides)))
        if state is not None:
            step = evals[-1][0] if evals else 0
            (d / "status.json").write_text(
                json.dumps(
                    {
                        "state": state,
                        "global_step": step,
                        "reason": "boom" if state == "failed" else "",
                    }
                )
            )
        lines = [
            {
                "step": s,
                "time": 0.0,
                "perf/sps": 1.0,
                "perf/collect_time": 0.5,
                "perf/update_time": 0.25,
            }
            for s, _ in evals
        ]
        lines += [{"step": s, "time": 0.0, "eval/episode_return": v} for s, v in evals]
        (d / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))

    for seed, final in enumerate([1.0, 2.0, 3.0, 100.0]):
        # step 100 logged twice (a resumed attempt re-logs it): the later value wins.
        job(seed, [f"seed={seed}", "lr=1"], "finished", [(100, -5.0), (100, 0.0), (200, final)])
    job(4, ["seed=0", "lr=2"], "failed", [(100, 7.0)])
    job(5, ["seed=1", "lr=2"], None, [])
    md = report(tmp_path)
    with open(tmp_path / "report.csv") as f:
        table = {r["configuration"]: r for r in csv.DictReader(f)}
    # IQM: the mean of the middle two of 1, 2, 3, 100.
    assert float(table["lr=1"]["iqm"]) == pytest.approx(2.5)
    assert float(table["lr=1"]["final_mean"]) == pytest.approx(26.5)
    assert float(table["lr=1"]["time_s"]) == pytest.approx(1.5)  # 2 steps x 0.75 s, step 100 once
    assert int(table["lr=2"]["n_seeds"]) == 0 and int(table["lr=2"]["n_unfinished"]) == 2
    assert math.isnan(float(table["lr=2"]["final_mean"]))
    assert "Unfinished or failed jobs (2)" in md
    assert "| `4` | `seed=0 lr=2` | failed | 100 | boom |" in md
    assert "| `5` | `seed=1 lr=2` | missing | 0 |" in md
    assert (tmp_path / "curves.png").exists()


def test_optuna_sweeper_runs_three_trials_on_the_final_eval_return(tmp_path):
    sweep = tmp_path / "sweep"
    run_train(
        [
            "-m",
            "+sweep=ppo_optuna",
            "hydra.sweeper.n_trials=3",
            *SWEEP_TINY,
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=tmp_path,
    )
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    assert [p.name for p in jobs] == ["0", "1", "2"]
    results = OmegaConf.load(sweep / "optimization_results.yaml")
    assert results.best_value == pytest.approx(max(final_eval(j) for j in jobs))
    assert set(results.best_params) == {
        "algorithm.lr",
        "algorithm.clip_epsilon",
        "algorithm.entropy_coeff",
    }


def test_local_parallel_launcher_runs_jobs_with_one_torch_thread(tmp_path):
    sweep = tmp_path / "sweep"
    run_train(
        ["-m", "hydra/launcher=local", "seed=0,1", *SWEEP_TINY, f"hydra.sweep.dir={sweep}"],
        cwd=tmp_path,
    )
    for n in ("0", "1"):
        assert json.loads((sweep / n / "status.json").read_text())["state"] == "finished"
        assert OmegaConf.load(sweep / n / "config.yaml").trainer.torch_threads == 1
        # What the job's process really ran with (torch.get_num_threads(), logged by the job).
        used = re.findall(r"torch threads (\d+)\)", (sweep / n / "train.log").read_text())
        assert used == ["1"], f"job {n} logged torch threads {used}"
    launcher = OmegaConf.load(sweep / "multirun.yaml").hydra.launcher
    assert launcher._target_.endswith("JoblibLauncher") and launcher.n_jobs == 2


@pytest.mark.parametrize(
    "override",
    [
        *(f"+sweep={p.stem}" for p in sorted((CONF_DIR / "sweep").glob("*.yaml"))),
        *(f"hydra/launcher={p.stem}" for p in sorted((CONF_DIR / "hydra/launcher").glob("*.yaml"))),
    ],
)
def test_sweep_and_launcher_configs_compose(override):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from rlexp.config.schema import register_configs

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[override], return_hydra_config=True)
    if override.startswith("+sweep="):
        assert cfg.hydra.sweeper.params
    else:
        assert cfg.hydra.launcher._target_.startswith("hydra_plugins.")


# -- a sweep with failing jobs: the others run, the failures are recorded, the sweep exits 1 --------

#: Jobs 0 and 2 (clip_epsilon=inf) fail their config check; jobs 1 and 3 train.
FAILING_GRID = ["seed=0,1", "algorithm.clip_epsilon=inf,0.2"]
CLIP_INF = "config error: algorithm.clip_epsilon=inf must be a finite number"


def report_cli(sweep: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rlexp.cli", "report", str(sweep), "--no-plot"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(REPO / "src")},
    )


@pytest.fixture(scope="module", params=["basic", "joblib"])
def failing_sweep(request, tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """``-m seed=0,1 algorithm.clip_epsilon=inf,0.2`` with Hydra's basic launcher (one process) or
    ``hydra/launcher=local`` (joblib worker processes)."""
    root = tmp_path_factory.mktemp(f"failing_{request.param}")
    sweep = root / "sweep"
    launcher = ["hydra/launcher=local"] if request.param == "joblib" else []
    args = ["-m", *launcher, *FAILING_GRID, *SWEEP_TINY, f"hydra.sweep.dir={sweep}"]
    return sweep, run_train(args, cwd=root, check=False)


def test_a_failing_job_does_not_stop_the_sweep_and_the_sweep_exits_1(failing_sweep):
    from rlexp.launch.sweep import EXIT_JOBS_FAILED

    sweep, proc = failing_sweep
    out = proc.stdout + proc.stderr
    assert proc.returncode == EXIT_JOBS_FAILED == 1, out[-3000:]
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1", "2", "3"]
    for n in ("0", "2"):
        status = json.loads((sweep / n / "status.json").read_text())
        assert status["state"] == "failed" and status["reason"] == CLIP_INF, status
        assert status["exit_code"] == 2
        assert not (sweep / n / "checkpoints").exists()
    for n in ("1", "3"):
        status = json.loads((sweep / n / "status.json").read_text())
        assert status["state"] == "finished" and status["global_step"] == 512
    summary = (
        f"sweep {sweep}: 2 of 4 jobs finished; 2 failed: {sweep / '0'} ({CLIP_INF}), "
        f"{sweep / '2'} ({CLIP_INF}) (rlexp report {sweep})"
    )
    assert summary in out
    assert "Traceback" not in out


def test_report_counts_the_expected_jobs_and_lists_failed_and_never_started_ones(
    failing_sweep, tmp_path
):
    from rlexp.launch.sweep import summarize_sweep

    sweep, _ = failing_sweep
    proc = report_cli(sweep)
    assert proc.returncode == 0, proc.stderr
    md = proc.stdout
    assert "4 jobs expected (multirun.yaml: the grid of the sweep's overrides), 4 started" in md
    assert "2 finished, 2 failed or unfinished, 0 never started" in md
    assert "## Unfinished or failed jobs (2)" in md and "## Never started (0)" in md
    for n, seed in (("0", 0), ("2", 1)):
        assert f"| `{n}` | `seed={seed} algorithm.clip_epsilon=inf env=inverted_pendulum" in md
    assert md.count(f"| failed | 0 | {CLIP_INF} |") == 2

    # Job 3's dir gone (a sweep stopped before it): expected from multirun.yaml, never started.
    copy = tmp_path / "sweep"
    shutil.copytree(sweep, copy)
    shutil.rmtree(copy / "3")
    md = report_cli(copy).stdout
    assert "4 jobs expected" in md and "3 started, 1 finished" in md and "1 never started" in md
    assert "## Never started (1)" in md
    assert f"| #3 | `seed=1 algorithm.clip_epsilon=0.2 {' '.join(SWEEP_TINY)}` |" in md
    line, ok = summarize_sweep(copy, OmegaConf.load(copy / "multirun.yaml"))
    assert not ok and line.startswith(f"sweep {copy}: 1 of 4 jobs finished; 2 failed: ")
    assert "; 1 never started: #3 (seed=1 algorithm.clip_epsilon=0.2 " in line


def test_optuna_goes_on_after_a_failed_trial(tmp_path):
    sweep = tmp_path / "sweep"
    proc = run_train(
        [
            "-m",
            "+sweep=ppo_optuna",
            "hydra.sweeper.n_trials=4",
            "algorithm.clip_epsilon=choice(inf,0.2)",
            *SWEEP_TINY,
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=tmp_path,
        check=False,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out[-3000:]
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    assert [p.name for p in jobs] == ["0", "1", "2", "3"]
    states = {p.name: json.loads((p / "status.json").read_text()) for p in jobs}
    failed = [n for n, s in states.items() if s["state"] == "failed"]
    done = [n for n, s in states.items() if s["state"] == "finished"]
    assert failed and done and len(failed) + len(done) == 4, states
    assert all(states[n]["reason"] == CLIP_INF for n in failed)
    results = OmegaConf.load(sweep / "optimization_results.yaml")
    assert results.best_value == pytest.approx(max(final_eval(sweep / n) for n in done))
    assert f"sweep {sweep}: {len(done)} of 4 jobs finished; {len(failed)} failed: " in out
    md = report_cli(sweep).stdout
    assert "4 jobs expected (multirun.yaml: hydra.sweeper.n_trials), 4 started" in md


def test_slurm_launcher_collects_every_job_when_one_died_without_a_result(tmp_path, monkeypatch):
    """A job killed by SLURM (here: out of memory) makes submitit's ``results()`` raise; the
    launcher still returns every job, records the dead one as failed, and says so in one line."""
    import logging

    import submitit
    from hydra.core.utils import JobReturn, JobStatus
    from submitit.core.utils import UncompletedJobError

    from hydra_plugins.rlexp_launcher.slurm_launcher import RlexpSlurmLauncher

    class Job:
        def __init__(self, job_id: str, value=None, error: Exception | None = None) -> None:
            self.job_id, self.value, self.error = job_id, value, error
            self.paths = type("P", (), {"stderr": tmp_path / f"{job_id}_0_log.err"})()

        def results(self):
            if self.error is not None:
                raise self.error
            ret = JobReturn(status=JobStatus.COMPLETED)
            ret.return_value = self.value
            return [ret]

    oom = UncompletedJobError(
        "Job 7_1 (task: 0) with path /x/7_1_0_result.pkl\nhas not produced any output "
        "(state: OUT_OF_MEMORY)\nError stream produced:\n----------\nKilled"
    )
    jobs = [Job("7_0", 1.5), Job("7_1", error=oom), Job("7_2", error=oom), Job("7_3", 2.5)]

    class Executor:
        def __init__(self, **kwargs) -> None: ...

        def update_parameters(self, **kwargs) -> None: ...

        def map_array(self, fn, *args):
            return jobs

    class Loader:  # the job's config, as load_sweep_config composes it
        def load_sweep_config(self, config, overrides):
            return OmegaConf.create(
                {"hydra": {"sweep": {"dir": str(sweep), "subdir": "${hydra.job.num}"}, "job": {}}}
            )

    sweep = tmp_path / "sweep"
    (sweep / "1").mkdir(parents=True)  # job 1 was training when it was killed
    (sweep / "1/status.json").write_text(json.dumps({"state": "running", "global_step": 256}))
    (sweep / "2").mkdir()  # job 2 had already recorded its own end: that stays
    (sweep / "2/status.json").write_text(json.dumps({"state": "stopped", "global_step": 128}))
    monkeypatch.setattr(submitit, "AutoExecutor", Executor)
    launcher = RlexpSlurmLauncher(submitit_folder=str(sweep / ".submitit/%j"), max_num_timeout=1)
    launcher.config = OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep)}}})
    launcher.hydra_context = type("C", (), {"config_loader": Loader()})()
    records = []
    handler = logging.Handler(logging.ERROR)
    handler.emit = records.append
    logging.getLogger("hydra_plugins.rlexp_launcher.slurm_launcher").addHandler(handler)
    try:
        returns = launcher.launch([["seed=0"], ["seed=1"], ["seed=2"], ["seed=3"]], 0)
    finally:
        logging.getLogger("hydra_plugins.rlexp_launcher.slurm_launcher").removeHandler(handler)

    assert [r.return_value for r in returns] == [1.5, None, None, 2.5]  # none raises
    status = json.loads((sweep / "1/status.json").read_text())
    reason = (
        "SLURM job 7_1 ended without a result: Job 7_1 (task: 0) with path "
        "/x/7_1_0_result.pkl has not produced any output (state: OUT_OF_MEMORY)"
    )
    assert status["state"] == "failed" and status["global_step"] == 256
    assert status["reason"] == reason
    assert json.loads((sweep / "2/status.json").read_text())["state"] == "stopped"
    assert [r.getMessage() for r in records][0] == (
        f"job #1: {reason}; its output: {tmp_path / '7_1_0_log.err'}"
    )
    assert len(records) == 2


@pytest.mark.slurm
@pytest.mark.usefixtures("cluster")  # skips when no SLURM cluster answers
def test_slurm_sweep_runs_the_other_jobs_past_a_failing_one_and_exits_1(tmp_path):
    sweep = tmp_path / "sweep"
    proc = run_train(
        [
            "-m",
            *SLURM,
            "seed=0",
            "algorithm.clip_epsilon=inf,0.2",
            *SWEEP_TINY,
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=tmp_path,
        check=False,
        timeout=300,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out[-3000:]
    failed = json.loads((sweep / "0/status.json").read_text())
    assert failed["state"] == "failed" and failed["reason"] == CLIP_INF
    assert json.loads((sweep / "1/status.json").read_text())["state"] == "finished"
    assert f"sweep {sweep}: 1 of 2 jobs finished; 1 failed: {sweep / '0'} ({CLIP_INF})" in out
