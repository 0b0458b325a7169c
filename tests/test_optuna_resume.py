"""Resumable Optuna sweeps (+sweep=ppo_optuna: hydra/sweeper=optuna, its study in the sweep dir's
optuna.journal): a 6-trial sweep killed (SIGKILL to its whole process group) while its 4th trial
trains, then the same command again: the study ends with 6 trials in 6 job dirs, the first 3
untouched, the killed one re-run in its dir. Also: trials that fail are told FAIL and a sweep where
all fail ends with rlexp's summary, not a traceback; a re-run retries them in their dirs; the
sweep's batching and work plan; rlexp report's trial table."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import REPO, SWEEP_TINY, Children, run_train

#: The batches of before asynchronous trials (#50): this module's killed sweep leaves a finished
#: trial RUNNING beside the one it killed (an asynchronous study: tests/test_optuna_async.py).
BATCHES = ("hydra.sweeper.async_trials=false",)
#: A trial trains 512 env steps of InvertedPendulum (about a second), without TensorBoard.
TINY = [*SWEEP_TINY, "logger=none"]


def command(sweep: Path, n_trials: int, *extra: str) -> list[str]:
    return [
        "-m",
        "+sweep=ppo_optuna",
        f"hydra.sweeper.n_trials={n_trials}",
        *extra,
        *TINY,
        f"hydra.sweep.dir={sweep}",
    ]


def study_trials(sweep: Path, storage: str | None = None) -> list[dict]:
    """The study's trials read with optuna alone (not through rlexp), from the sweep dir's journal
    file (or ``storage``): number, state, value, params, user attrs."""
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    if storage is None:
        assert (sweep / "optuna.journal").is_file(), sorted(p.name for p in sweep.iterdir())
        storage = JournalStorage(JournalFileBackend(str(sweep / "optuna.journal")))
    (name,) = optuna.get_all_study_names(storage)
    return [
        {
            "number": t.number,
            "state": t.state.name,
            "value": t.value if t.values is not None and len(t.values) == 1 else None,
            "params": dict(t.params),
            "attrs": dict(t.user_attrs),
        }
        for t in optuna.load_study(study_name=name, storage=storage).get_trials(deepcopy=False)
    ]


def status(job: Path) -> dict:
    try:
        return json.loads((job / "status.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return {}


def tree(directory: Path) -> dict[str, tuple[int, int, str]]:
    """Every file under ``directory``: size, mtime and content hash."""
    return {
        str(p.relative_to(directory)): (
            p.stat().st_size,
            p.stat().st_mtime_ns,
            hashlib.sha256(p.read_bytes()).hexdigest(),
        )
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def overrides(job: Path) -> dict[str, str]:
    from omegaconf import OmegaConf

    return dict(o.split("=", 1) for o in OmegaConf.load(job / ".hydra" / "overrides.yaml"))


@pytest.fixture(scope="module")
def killed_and_rerun(tmp_path_factory) -> dict:
    """``-m +sweep=ppo_optuna hydra.sweeper.n_trials=6`` in batches, SIGKILLed (process group) once trials
    0-2 have finished and trial 3 is training; then the same command to its end."""
    root = tmp_path_factory.mktemp("optuna_resume")
    sweep = root / "sweep"
    with Children() as children:  # the sweep's group (its jobs too) killed however this ends
        proc = children.train(command(sweep, 6, *BATCHES), root, root / "first.log")
        deadline = time.monotonic() + 240
        while status(sweep / "3").get("state") != "running":
            assert proc.poll() is None, (root / "first.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "trial 3 never started"
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    before = {
        "trials": study_trials(sweep),
        "dirs": {n: tree(sweep / n) for n in ("0", "1", "2")},
        "status2": status(sweep / "2"),
        "status3": status(sweep / "3"),
        "ckpts3": sorted(p.name for p in (sweep / "3" / "checkpoints").glob("*.pt")),
    }
    start = time.monotonic()
    second = run_train(command(sweep, 6, *BATCHES), cwd=root)
    return {
        "sweep": sweep,
        "before": before,
        "second": second.stdout + second.stderr,
        "second_s": time.monotonic() - start,
    }


def test_the_killed_sweep_is_in_the_study_as_it_was_left(killed_and_rerun):
    before = killed_and_rerun["before"]
    # Trials 2 and 3 are one batch (hydra.sweeper.n_jobs=2): a launcher returns a batch's results
    # together, so trial 2 is still RUNNING in the study although its job had finished.
    states = [t["state"] for t in before["trials"]]
    assert states == ["COMPLETE", "COMPLETE", "RUNNING", "RUNNING"], before["trials"]
    assert [t["attrs"]["rlexp_job"] for t in before["trials"]] == [0, 1, 2, 3]
    assert before["status2"]["state"] == "finished"
    assert before["status3"]["state"] == "running"


def test_the_same_command_continues_the_sweep_to_n_trials_in_all(killed_and_rerun):
    sweep, before = killed_and_rerun["sweep"], killed_and_rerun["before"]
    after = study_trials(sweep)
    assert [t["number"] for t in after] == [0, 1, 2, 3, 4, 5]
    assert [t["state"] for t in after] == ["COMPLETE"] * 6
    assert [t["attrs"]["rlexp_job"] for t in after] == [0, 1, 2, 3, 4, 5]
    jobs = sorted((p for p in sweep.iterdir() if p.is_dir()), key=lambda p: int(p.name))
    assert [p.name for p in jobs] == ["0", "1", "2", "3", "4", "5"]
    for job, trial in zip(jobs, after, strict=True):
        assert status(job)["state"] == "finished" and status(job)["global_step"] == 512
        # the trial's parameters are the job's overrides, exactly, in the search space's order,
        # and its value is the job's final eval
        ov = overrides(job)
        keys = ["algorithm.lr", "algorithm.clip_epsilon", "algorithm.entropy_coeff"]
        assert list(ov)[:3] == keys
        for key in keys:
            assert float(ov[key]) == trial["params"][key]
        assert trial["value"] == status(job)["final_eval"]["eval/episode_return"]
    # trials 0-2 and their job dirs: untouched (not launched again); trial 2 told its dir's result
    assert after[:2] == before["trials"][:2]
    assert after[2]["params"] == before["trials"][2]["params"]
    for n in ("0", "1", "2"):
        assert tree(sweep / n) == before["dirs"][n], f"job dir {n} changed"
    out = killed_and_rerun["second"]
    launched = [line.split("#", 1)[1].split(" :")[0] for line in out.splitlines() if "\t#" in line]
    assert launched == ["3", "4", "5"], out[-3000:]
    assert "trial 2: its job dir 2 had finished (eval/episode_return = " in out
    assert "3 trial(s) kept, 1 killed to re-run, 0 failed to retry, 2 new (n_trials=6)" in out
    assert f"sweep {sweep}: 6 of 6 jobs finished" in out


def test_the_killed_trial_is_re_run_in_place_with_its_parameters(killed_and_rerun):
    sweep, before = killed_and_rerun["sweep"], killed_and_rerun["before"]
    killed = before["trials"][3]
    after = study_trials(sweep)[3]
    assert after["params"] == killed["params"]  # the same trial, re-run, not a new one
    log = (sweep / "3" / "train.log").read_text()
    assert log.count("run dir: ") == 2, log  # two attempts in one dir
    if before["ckpts3"]:  # killed after its first checkpoint: the re-run continued from it
        rows = [json.loads(x) for x in (sweep / "3" / "metrics.jsonl").read_text().splitlines()]
        assert rows[-1]["step"] == 512


def test_a_resumed_study_proposes_new_parameters(killed_and_rerun):
    """The sampler is reseeded on resume: TPE's seeded start would repeat trials 0 and 1."""
    trials = study_trials(killed_and_rerun["sweep"])
    proposed = {tuple(sorted(t["params"].items())) for t in trials}
    assert len(proposed) == 6


def test_report_lists_the_trials_with_parameters_and_values(killed_and_rerun):
    sweep = killed_and_rerun["sweep"]
    proc = subprocess.run(
        [sys.executable, "-m", "rlexp", "report", str(sweep), "--no-plot"],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO / "src")},
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    md = proc.stdout
    assert "6 jobs expected (multirun.yaml: hydra.sweeper.n_trials), 6 started, 6 finished" in md
    assert "## Optuna trials (study `ppo`: 6 trials, 6 complete)" in md
    for t in study_trials(sweep):
        value = f"{t['value']:.2f}"
        assert f"| {t['number']} | `{t['attrs']['rlexp_job']}` | COMPLETE | {value} |" in md


def test_a_sweep_whose_trials_all_fail_ends_with_the_summary_and_retries_them(tmp_path):
    sweep = tmp_path / "sweep"
    cmd = command(sweep, 2, "algorithm.clip_epsilon=inf")
    first = run_train(cmd, cwd=tmp_path, check=False)
    out = first.stdout + first.stderr
    assert first.returncode == 1, out[-3000:]
    assert "Traceback" not in out
    assert f"sweep {sweep}: 0 of 2 jobs finished; 2 failed: {sweep / '0'} (config error:" in out
    assert not (sweep / "optimization_results.yaml").exists()
    assert [t["state"] for t in study_trials(sweep)] == ["FAIL", "FAIL"]

    # the same command: each failed trial retried once, with its parameters, in its own dir
    second = run_train(cmd, cwd=tmp_path, check=False)
    out = second.stdout + second.stderr
    assert second.returncode == 1 and "Traceback" not in out, out[-3000:]
    assert "0 trial(s) kept, 0 killed to re-run, 2 failed to retry, 0 new (n_trials=2)" in out
    trials = study_trials(sweep)
    assert [t["state"] for t in trials] == ["FAIL"] * 4
    assert [t["attrs"]["rlexp_job"] for t in trials] == [0, 1, 0, 1]
    assert [t["attrs"].get("rlexp_retry_of") for t in trials] == [None, None, 0, 1]
    assert trials[2]["params"] == trials[0]["params"] and trials[3]["params"] == trials[1]["params"]
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1"]


def test_a_second_sweep_into_a_dir_in_use_is_refused(tmp_path):
    from rlexp.launch.optuna_sweeper import SweepLock, SweepRefused

    first = SweepLock(tmp_path)
    first.acquire()
    try:
        with pytest.raises(SweepRefused, match="in use by another Optuna sweep"):
            SweepLock(tmp_path).acquire()
    finally:
        first.release()
    SweepLock(tmp_path).acquire()  # free again


def test_work_plan_and_batches():
    """Per job dir its latest trial decides; new trials fill up to n_trials; a launch call gets
    consecutive job numbers only."""
    from types import SimpleNamespace as T

    from optuna.trial import TrialState as S

    from rlexp.launch.optuna_sweeper import batches, plan_work

    def t(number, state, job=None, legacy=False):
        attrs = {} if job is None else {"rlexp_job": job}
        # legacy: a study of an rlexp before optuna 4 kept the job as a system attr
        return T(number=number, state=state, user_attrs={} if legacy else attrs,
                 system_attrs=attrs if legacy else {})  # fmt: skip

    trials = [
        t(0, S.COMPLETE, 0, legacy=True),
        t(1, S.FAIL, 1),
        t(2, S.FAIL, 2),
        t(3, S.RUNNING, 3),
        t(4, S.COMPLETE, 1),  # job 1's retry finished
        t(5, S.FAIL),  # not one of rlexp's: ignored
    ]
    work, heads = plan_work(trials, 6)
    assert [(w.kind, w.job) for w in work] == [
        ("retry", 2),
        ("resume", 3),
        ("new", 4),
        ("new", 5),
    ]
    assert heads[1].number == 4 and work[0].retry_of.number == 2 and heads[0].number == 0
    assert [[w.job for w in b] for b in batches(work, 2)] == [[2, 3], [4, 5]]
    assert [[w.job for w in b] for b in batches(work, 3)] == [[2, 3, 4], [5]]
    assert (
        plan_work(trials, 2)[0][-1].kind == "resume"
    )  # fewer n_trials: nothing new, still resumed
