"""Confirmation of an Optuna search on fresh seeds (#50 item 3): the plan (top_k, fresh seeds
disjoint from every trial's, job numbers kept on a re-run), the ranking by IQM over the fresh
seeds and the search's optimism, the winner's preset (composes and equals the winner's config),
the refusals, and a real sweep that confirms and resumes."""

from __future__ import annotations

import json
import math
import zlib
from pathlib import Path

import numpy as np
import optuna
import pytest
from omegaconf import OmegaConf
from optuna.distributions import FloatDistribution, IntDistribution
from optuna.trial import TrialState, create_trial
from scipy.stats import trim_mean
from test_optuna_async import study_of

from conftest import Children
from rlexp.analysis.reporting.confirm import (
    ConfirmError,
    confirm_lines,
    read_confirmation,
    write_preset,
)
from rlexp.launch.optuna_confirm import (
    CONFIRM_JOB_BASE,
    ConfirmSettings,
    confirm_settings,
    fresh_seeds,
    job_overrides,
    plan,
)
from rlexp.launch.optuna_study import StudyConfigError

LR = FloatDistribution(1e-5, 1e-2, log=True)


def _trial(number: int, value: float | None, lr: float, seeds: list[int], **params) -> object:
    dists = {"algorithm.lr": LR, **{k: IntDistribution(0, 10**7) for k in params}}
    t = create_trial(
        params={"algorithm.lr": lr, **params},
        distributions=dists,
        value=value,
        state=TrialState.COMPLETE if value is not None else TrialState.FAIL,
        user_attrs={
            "rlexp_job": number,
            "rlexp_jobs": [number * 10 + k for k in range(len(seeds))],
            "rlexp_seeds": seeds,
            "rlexp_overrides": [f"algorithm.lr={lr}", "env=pendulum"],
        },
    )
    t.number = number
    return t


def test_fresh_seeds_skip_every_used_seed_and_depend_on_the_study_name_only():
    start = 1_000_000 + zlib.crc32(b"hopper_tpe") % 1_000_000
    assert fresh_seeds("hopper_tpe", {start, start + 2}, 3) == [start + 1, start + 3, start + 4]
    assert fresh_seeds("hopper_tpe", set(), 2) == [start, start + 1]
    assert fresh_seeds("other", set(), 1) != fresh_seeds("hopper_tpe", set(), 1)


def test_the_plan_takes_the_top_k_in_the_study_direction_with_seeds_no_trial_used():
    name = "s"
    start = 1_000_000 + zlib.crc32(name.encode()) % 1_000_000
    # trial 1 ran two seeds (trial_seeds=2), one of them the first fresh candidate; trial 3
    # searched its seed and drew the second one; trial 4 failed
    trials = [
        _trial(0, -5.0, 1e-3, [0]),
        _trial(1, -9.0, 2e-3, [0, start]),
        _trial(2, -1.0, 3e-3, [0]),
        _trial(3, -7.0, 4e-3, [start + 1], seed=start + 1),
        _trial(4, None, 5e-3, [start + 2]),
    ]
    found = plan(trials, trials, ConfirmSettings(2, 3), name, "minimize", 0, None)
    # minimize: the two lowest values, best first
    assert [c["trial"] for c in found["candidates"]] == [1, 3]
    assert [c["search_value"] for c in found["candidates"]] == [-9.0, -7.0]
    # seeds: none of any trial's (the failed one's too), the same for both configurations
    assert found["seeds"] == [start + 3, start + 4, start + 5]
    used = {s for t in trials for s in t.user_attrs["rlexp_seeds"]}
    assert not used & set(found["seeds"])
    jobs = [j["job"] for c in found["candidates"] for j in c["jobs"]]
    assert jobs == list(range(CONFIRM_JOB_BASE, CONFIRM_JOB_BASE + 6))
    # a searched seed is replaced by the fresh one in the job's overrides
    c3 = found["candidates"][1]
    c3["overrides"] = [*c3["overrides"], f"seed={start + 1}"]
    assert job_overrides(c3, 77) == [f"algorithm.lr={4e-3}", "env=pendulum", "seed=77"]
    # maximize picks the other end
    up = plan(trials, trials, ConfirmSettings(1, 1), name, "maximize", 0, None)
    assert [c["trial"] for c in up["candidates"]] == [2]


def test_a_re_plan_keeps_the_job_numbers_it_had_and_numbers_new_pairs_above_them():
    trials = [_trial(0, 1.0, 1e-3, [0]), _trial(1, 3.0, 2e-3, [0]), _trial(2, 2.0, 3e-3, [0])]
    first = plan(trials, trials, ConfirmSettings(1, 2), "s", "maximize", 0, None)
    assert [(c["trial"], [j["job"] for j in c["jobs"]]) for c in first["candidates"]] == [
        (1, [CONFIRM_JOB_BASE, CONFIRM_JOB_BASE + 1])
    ]
    second = plan(trials, trials, ConfirmSettings(2, 2), "s", "maximize", 0, first)
    assert [(c["trial"], [j["job"] for j in c["jobs"]]) for c in second["candidates"]] == [
        (1, [CONFIRM_JOB_BASE, CONFIRM_JOB_BASE + 1]),
        (2, [CONFIRM_JOB_BASE + 2, CONFIRM_JOB_BASE + 3]),
    ]


@pytest.mark.parametrize(
    "value, message",
    [
        ({"top_k": 0}, "hydra.sweeper.confirm.top_k=0: a whole number >= 1"),
        ({"seeds": 0}, "hydra.sweeper.confirm.seeds=0: a whole number >= 1"),
        ({"seeds": 2.5}, "hydra.sweeper.confirm.seeds=2.5: a whole number >= 1"),
        ({"top": 2}, "hydra.sweeper.confirm.top: no such key (confirm takes top_k and seeds)"),
        (3, "hydra.sweeper.confirm=3: a mapping {top_k: K, seeds: S}, or null"),
    ],
)
def test_confirm_settings_refusals_name_the_key(value, message):
    with pytest.raises(StudyConfigError) as err:
        confirm_settings(value, 1)
    assert str(err.value) == message


def test_confirm_is_refused_for_a_multi_objective_study():
    with pytest.raises(StudyConfigError, match="the study has 2 objectives"):
        confirm_settings({"top_k": 1, "seeds": 2}, 2)
    assert confirm_settings(None, 2) is None
    assert confirm_settings({"seeds": 3}, 1) == ConfirmSettings(1, 3)


def _fake_sweep(root: Path, values: dict[int, list[float]], search: dict[int, float]) -> Path:
    """A sweep dir with confirm.json and finished confirmation jobs holding ``values``."""
    candidates, job = [], CONFIRM_JOB_BASE
    for rank, (trial, vals) in enumerate(values.items(), 1):
        jobs = []
        for k, v in enumerate(vals):
            d = root / str(job)
            d.mkdir(parents=True)
            status = {"state": "finished", "final_eval": {"eval/episode_return": v}}
            (d / "status.json").write_text(json.dumps(status))
            jobs.append({"job": job, "seed": 100 + k})
            job += 1
        candidates.append(
            {
                "search_rank": rank,
                "trial": trial,
                "search_value": search[trial],
                "params": {"algorithm.lr": trial / 1000},
                "overrides": [],
                "jobs": jobs,
            }
        )
    plan_ = {"version": 1, "study": "s", "direction": "maximize", "top_k": len(values)}
    plan_ |= {"seeds": [100, 101, 102, 103], "candidates": candidates}
    (root / "confirm.json").write_text(json.dumps(plan_))
    return root


def test_the_report_ranks_by_the_iqm_over_the_fresh_seeds_and_shows_the_optimism(tmp_path):
    # search ranks trial 7 first (its own seed: 95); on fresh seeds trial 3 is better
    values = {7: [10.0, 80.0, 20.0, 30.0], 3: [50.0, 40.0, 60.0, 1.0]}
    sweep = _fake_sweep(tmp_path, values, {7: 95.0, 3: 70.0})
    plan_, rows = read_confirmation(sweep)
    expected = {t: float(trim_mean(v, 0.25)) for t, v in values.items()}
    assert expected == {7: 25.0, 3: 45.0}  # by hand: mean of the middle two
    assert [r.trial for r in rows] == [3, 7]
    assert [r.iqm for r in rows] == [45.0, 25.0]
    assert all(r.ci[0] <= r.iqm <= r.ci[1] for r in rows)
    text = "\n".join(confirm_lines(sweep))
    assert "| 1 | 3 | 2 | 70 | 45 |" in text and "| 2 | 7 | 1 | 95 | 25 |" in text
    assert "its best trial scored 95 on its own seed(s) and 25 (IQM) on the fresh seeds: 70" in text


def test_an_unfinished_confirmation_job_is_not_counted(tmp_path):
    sweep = _fake_sweep(tmp_path, {1: [1.0, 2.0, 3.0]}, {1: 9.0})
    (sweep / str(CONFIRM_JOB_BASE + 2) / "status.json").write_text('{"state": "running"}')
    _, rows = read_confirmation(sweep)
    assert rows[0].values == [1.0, 2.0] and rows[0].iqm == pytest.approx(1.5)


def test_write_preset_refusals(tmp_path):
    with pytest.raises(ConfirmError, match="no confirm.json: run the sweep with hydra.sweeper"):
        write_preset(tmp_path, tmp_path / "p.yaml")
    sweep = _fake_sweep(tmp_path / "s", {1: [1.0]}, {1: 2.0})
    (tmp_path / "p.yaml").write_text("x: 1\n")
    with pytest.raises(ConfirmError, match="the file exists \\(add --force to replace it\\)"):
        write_preset(sweep, tmp_path / "p.yaml")
    with pytest.raises(ConfirmError, match="a .yaml file"):
        write_preset(sweep, tmp_path / "p.txt")


# -- a real sweep ---------------------------------------------------------------------------------

TINY = [
    "env=inverted_pendulum",
    "trainer.frames_per_batch=256",
    "trainer.total_frames=512",
    "algorithm.num_epochs=1",
    "trainer.eval_episodes=2",
    "logger=none",
]


def _command(sweep: Path, *extra: str) -> list[str]:
    return [
        "-m",
        "+sweep=ppo_optuna",
        "hydra/launcher=local",
        "hydra.sweeper.n_trials=3",
        "+hydra.sweeper.confirm={top_k:2,seeds:2}",
        "algorithm.gamma=0.97",  # a fixed override: part of the winner's preset
        *TINY,
        *extra,
        f"hydra.sweep.dir={sweep}",
    ]


def _sweep(cmd: list[str], cwd: Path, name: str) -> str:
    """The sweep's console; its process group (the jobs too) is killed however this ends."""
    log = cwd / f"{name}.log"
    with Children() as children:
        proc = children.train(cmd, cwd, log)
        proc.wait(timeout=600)
    out = log.read_text()
    assert proc.returncode == 0, out[-3000:]
    return out


def _configs_equal_but_the_runs_own(preset_cfg: dict, run_cfg: dict) -> list[str]:
    from rlexp.analysis.reporting.confirm import NOT_PRESET

    def flat(d: dict, path: str = "") -> dict:
        out = {}
        for k, v in d.items():
            where = f"{path}.{k}" if path else str(k)
            if isinstance(v, dict):
                out |= flat(v, where)
            else:
                out[where] = v
        return out

    a, b = flat(preset_cfg), flat(run_cfg)
    own = tuple(NOT_PRESET)
    keys = {k for k in a.keys() | b.keys() if not any(k == o or k.startswith(o + ".") for o in own)}
    return sorted(k for k in keys if a.get(k, "<missing>") != b.get(k, "<missing>"))


def test_a_real_sweep_confirms_on_fresh_seeds_resumes_and_writes_a_preset_that_composes(
    tmp_path,
):
    sweep = tmp_path / "s"
    out = _sweep(_command(sweep), tmp_path, "first")
    assert "Confirmation on fresh seeds" in out and "Traceback" not in out
    plan_ = json.loads((sweep / "confirm.json").read_text())
    trials = study_of(sweep).get_trials()
    trial_seeds = {s for t in trials for s in t.user_attrs["rlexp_seeds"]}
    assert len(plan_["seeds"]) == 2 and not trial_seeds & set(plan_["seeds"])
    done = sorted((t for t in trials if t.value is not None), key=lambda t: -t.value)
    assert [c["trial"] for c in plan_["candidates"]] == [t.number for t in done[:2]]
    jobs = [j for c in plan_["candidates"] for j in c["jobs"]]
    for j in jobs:  # each ran with its fresh seed and its trial's parameters
        cfg = OmegaConf.load(sweep / str(j["job"]) / "config.yaml")
        assert cfg.seed == j["seed"]
        st = json.loads((sweep / str(j["job"]) / "status.json").read_text())
        assert st["state"] == "finished"
    # one confirmation job lost (its dir removed): the same command trains it alone again
    lost = sweep / str(jobs[-1]["job"])
    import shutil

    shutil.rmtree(lost)
    log = _sweep(_command(sweep), tmp_path, "again")
    # the search's trials are done (not launched again); the finished confirmation jobs skip
    assert log.count("already finished at step 512: skipping") == len(jobs) - 1
    assert log.count(f"run dir: {lost} ") == 1
    assert json.loads((lost / "status.json").read_text())["state"] == "finished"
    assert json.loads((sweep / "confirm.json").read_text())["candidates"] == plan_["candidates"]

    # the winner as a preset in a user config dir: composes with the env and equals its config
    _, rows = read_confirmation(sweep)
    user = tmp_path / "myconf"
    write_preset(sweep, user / "tuned" / "ip_best.yaml")
    from hydra import compose

    from rlexp.config.paths import find_conf_dir, initialize_hydra
    from rlexp.config.schema import register_configs
    from rlexp.config.validate import to_root_config

    register_configs()
    with initialize_hydra(find_conf_dir(), str(user)):
        cfg = compose("config", overrides=["env=inverted_pendulum", "tuned=ip_best"])
    composed = OmegaConf.to_container(OmegaConf.structured(to_root_config(cfg)), resolve=True)
    winner = OmegaConf.to_container(
        OmegaConf.load(sweep / str(rows[0].jobs[0]) / "config.yaml"), resolve=True
    )
    assert _configs_equal_but_the_runs_own(composed, winner) == []
    assert composed["algorithm"]["gamma"] == 0.97
    assert math.isclose(composed["algorithm"]["lr"], rows[0].params["algorithm.lr"])
    assert np.isfinite(rows[0].iqm)
    assert optuna.__version__  # the study was read through optuna (imported above)


def test_confirm_without_an_optuna_study_is_one_line_before_anything_is_written(tmp_path):
    import subprocess
    import sys

    sweep = tmp_path / "s"
    proc = subprocess.run(
        [
            sys.executable,
            str(Path(__file__).resolve().parents[1] / "train.py"),
            "-m",
            "+hydra.sweeper.confirm={top_k:1,seeds:2}",
            "trainer=smoke",
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [x for x in proc.stderr.splitlines() if x.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].endswith(
        "hydra.sweeper.confirm: only rlexp's Optuna sweeper has it (hydra/sweeper=optuna, or "
        "+sweep=ppo_optuna); this sweep's sweeper "
        "'hydra._internal.core_plugins.basic_sweeper.BasicSweeper' keeps no study of trials"
    )
    assert not sweep.exists()


def test_the_plan_builds_overrides_from_the_search_space_not_from_text_in_the_study():
    """A study file is data: overrides recorded there (a tampered journal) never reach the jobs;
    a trial with a parameter outside the sweep's search space is not confirmed."""
    good = _trial(0, 5.0, 1e-3, [0])
    good.user_attrs["rlexp_overrides"] = ["+hydra.callbacks.x._target_=os.system", "seed=3"]
    foreign = _trial(1, 9.0, 2e-3, [0], **{"hydra.job.chdir": 1})
    custom = _trial(2, 7.0, 3e-3, [0], **{"trainer.frames_per_batch": 512})  # custom space
    found = plan(
        [good, foreign, custom],
        [good, foreign, custom],
        ConfirmSettings(3, 1),
        "s",
        "maximize",
        0,
        None,
        ["algorithm.lr"],
        {"env": "env=pendulum", "algorithm.gamma": "algorithm.gamma=0.97"},
    )
    assert [c["trial"] for c in found["candidates"]] == [2, 0]
    assert found["candidates"][0]["overrides"][:2] == [
        f"algorithm.lr={3e-3}",
        "trainer.frames_per_batch=512",
    ]
    assert found["candidates"][1]["overrides"] == [
        f"algorithm.lr={1e-3}",
        "env=pendulum",
        "algorithm.gamma=0.97",
    ]
