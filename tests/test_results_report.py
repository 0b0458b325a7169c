"""``rlexp report`` on a sweep over envs (the reference-results suite, ``+sweep=mujoco_1m``): per
env both result metrics (the last 100 training episodes, the final deterministic eval) as IQM with
its bootstrap interval, the published anchors where the task has one, wall time and env steps/s,
the time to the CleanRL mean (env steps and wall-clock, k/n seeds), eval success only for tasks
that define it, ``results.csv`` and the per-env figure. Job dirs are
written as rlexp writes them (overrides, config.yaml, provenance.json, status.json, metrics.jsonl);
the report's other parts: tests/test_report.py."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
from test_report import multirun_yaml, rlexp_report

from rlexp.analysis.report import (
    RESULT_METRICS,
    add_histories,
    anchors_for,
    bootstrap_ci,
    env_results,
    find_jobs,
    iqm,
    report,
)

#: Env option (the override) -> (env.name, env.backend), as conf/env/*.yaml.
ENVS = {
    "hopper": ("Hopper-v5", "gymnasium"),
    "ant": ("Ant-v5", "gymnasium"),
    "swimmer": ("Swimmer-v5", "gymnasium"),
    "inverted_pendulum": ("InvertedPendulum-v5", "gymnasium"),
    "reacher": ("Reacher-v5", "gymnasium"),
    "inverted_double_pendulum": ("InvertedDoublePendulum-v5", "gymnasium"),
    "cart_pole": ("cart_pole", "native"),
}
BATCH, BUDGET, EVAL_EVERY = 1000, 10_000, 5000
#: The first attempt's start (provenance.json's start_time of every job, unless ``start_s``).
START = datetime(2026, 11, 23, 10, tzinfo=timezone.utc).timestamp()
#: Seconds from the start to the end of the first iteration, before the batches' own time; an
#: eval row is written EVAL_S after its step's training row. Both exact in binary.
STARTUP_S, EVAL_S = 12.5, 2.25


def write_job(
    sweep: Path,
    num: int,
    overrides: list[str],
    train: float,
    evaluation: float,
    success: float = 0.0,
    wall_s: int = 600,
    state: str = "finished",
    batch_s: float = 30.0,
    start_s: int = 0,
    times: bool = True,
) -> Path:
    """A job dir as rlexp leaves it: training returns rising to ``train`` at the last iteration
    (every BATCH steps), evals every EVAL_EVERY steps ending at ``evaluation`` (and ``success``),
    started at 10:00:00 and ended ``wall_s`` later. Each row's ``time``: the training row of
    iteration i at START + STARTUP_S + i x ``batch_s``, its step's eval row (a row of its own, as
    the trainer writes it) EVAL_S later; none with ``times`` False (an older rlexp).
    ``start_s``: provenance.json's start that many seconds after 10:00:00 (a resumed job's last
    attempt: the rows before it are an earlier attempt's)."""
    d = sweep / str(num)
    (d / ".hydra").mkdir(parents=True)
    (d / ".hydra/overrides.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(overrides)))
    option = dict(o.split("=") for o in overrides)["env"]
    name, backend = ENVS[option]
    cfg = {
        "seed": 0,
        "trainer": {"total_frames": BUDGET, "iterations": None, "frames_per_batch": BATCH},
        "env": {"name": name, "backend": backend},
    }
    (d / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(cfg)))
    start = f"2026-11-23T10:{start_s // 60:02d}:{start_s % 60:02d}+0000"
    (d / "provenance.json").write_text(json.dumps({"start_time": start}))
    end = f"2026-11-23T10:{wall_s // 60:02d}:{wall_s % 60:02d}+0000"
    status = {"state": state, "global_step": BUDGET, "final_eval": {}, "time": end}
    (d / "status.json").write_text(json.dumps(status))
    rows = []
    for step in range(BATCH, BUDGET + 1, BATCH):
        t = START + STARTUP_S + step // BATCH * batch_s
        row = {"step": step, "train/episode_return": train * step / BUDGET, "perf/sps": 1000.0}
        rows.append(({"time": t} if times else {}) | row)
        if step % EVAL_EVERY == 0:
            row = {
                "step": step,
                "eval/episode_return": evaluation * step / BUDGET,
                "eval/success_rate": success * step / BUDGET,
            }
            rows.append(({"time": t + EVAL_S} if times else {}) | row)
    (d / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return d


#: Per env, five seeds' final training return and final eval return.
TRAIN = {
    "hopper": [1000.0, 2000.0, 3000.0, 4000.0, 5000.0],
    "ant": [500.0, 900.0, 1500.0, 2500.0, 2600.0],
    "swimmer": [40.0, 50.0, 60.0, 70.0, 80.0],
}
EVAL = {env: [v + 100.0 for v in values] for env, values in TRAIN.items()}
#: Wall seconds per seed: median 600 (10 min) for every env.
WALL = [500, 550, 600, 650, 700]
#: Seconds per iteration (BATCH steps) per seed.
BATCH_S = [20.0, 25.0, 30.0, 35.0, 40.0]
#: Hopper's seeds 2, 3, 4 reach CleanRL's 2382.86 (rising linearly to 3000, 4000, 5000) at steps
#: 8000, 6000, 5000 (an eval step: the training row's time, not its eval row's); 0 and 1 never.
HOPPER_REACHED = [8000, 6000, 5000]
HOPPER_REACHED_S = [STARTUP_S + 8 * 30.0, STARTUP_S + 6 * 35.0, STARTUP_S + 5 * 40.0]


@pytest.fixture
def env_sweep(tmp_path) -> Path:
    """env=hopper,ant,swimmer x seed=0..4 as the basic sweeper numbers them; ant seed 4 failed."""
    multirun_yaml(tmp_path, ["env=hopper,ant,swimmer", "seed=0,1,2,3,4"])
    num = 0
    for env in TRAIN:
        for seed in range(5):
            state = "failed" if (env, seed) == ("ant", 4) else "finished"
            overrides = [f"env={env}", f"seed={seed}"]
            train, evaluation = TRAIN[env][seed], EVAL[env][seed]
            write_job(
                tmp_path, num, overrides, train, evaluation, wall_s=WALL[seed], state=state,
                batch_s=BATCH_S[seed],
            )  # fmt: skip
            num += 1
    return tmp_path


def row_of(md: str, env: str) -> list[str]:
    """The cells of the results table's row of ``env``."""
    line = next(ln for ln in md.splitlines() if ln.startswith(f"| `{env}` |"))
    return [c.strip() for c in line.strip("|").split("|")]


def cells_of(md: str, env: str) -> dict[str, str]:
    """The cells of the results table's row of ``env``, by column header."""
    header = next(ln for ln in md.splitlines() if ln.startswith("| env |"))
    return dict(
        zip([c.strip() for c in header.strip("|").split("|")], row_of(md, env), strict=True)
    )


def results_of(sweep: Path):
    """``env_results`` of the sweep's jobs, as ``rlexp report`` reads them."""
    jobs = find_jobs(sweep)
    add_histories(jobs, RESULT_METRICS)
    return env_results(jobs)


def iqm_cell(values: list[float]) -> str:
    """``IQM [low, high]`` as the table shows it, from rlexp.analysis.stats' own functions."""
    x = np.array(values)
    low, high = bootstrap_ci(x, iqm)
    return f"{float(iqm(x)):.0f} [{low:.0f}, {high:.0f}]"


def test_job_dirs_give_their_env_backend_and_wall_time(env_sweep):
    jobs = find_jobs(env_sweep)
    assert [(j.env, j.backend) for j in jobs[:1]] == [("Hopper-v5", "gymnasium")]
    assert [j.env for j in jobs[5:6]] == ["Ant-v5"]
    assert [j.wall_s for j in jobs[:5]] == WALL


def test_a_sweep_over_envs_shows_both_metrics_anchors_and_time_per_env(env_sweep):
    md = report(env_sweep, plot=False)
    assert "## Results per env" in md
    # The section sits right after the configurations table, before the failed jobs.
    assert md.index("| configuration | seeds |") < md.index("## Results per env")
    assert md.index("## Results per env") < md.index("## Unfinished or failed jobs")
    header = row_of(md.replace("| env |", "| `env` |", 1), "env")
    assert header == [
        "`env`",
        "seeds",
        "train return: IQM [95% CI]",
        "train mean ± std",
        "CleanRL PPO (1)",
        "rlexp defaults (4)",
        "eval return: IQM [95% CI]",
        "eval mean ± std",
        "rl-zoo PPO (2)",
        "Tianshou PPO (3)",
        "rlexp defaults (5)",
        "wall per job (median)",
        "env steps/s (median)",
        "steps to CleanRL mean (median, seeds)",
        "wall to CleanRL mean (median)",
        "steps to rl-zoo eval mean (median, seeds)",
        "wall to rl-zoo mean (median)",
    ]

    hopper = row_of(md, "Hopper-v5")
    assert hopper[1] == "5"
    assert hopper[2] == iqm_cell(TRAIN["hopper"]) and hopper[2].startswith("3000 [")
    assert hopper[3] == "3000 ± 1581"  # std ddof 1
    assert hopper[4] == "2383 ± 272 (Hopper-v4)"  # CleanRL: last 100 training episodes
    assert hopper[5] == "2504 [2401, 2629] (Hopper-v5)"  # the defaults' train IQM, results.md
    assert hopper[6] == iqm_cell(EVAL["hopper"]) and hopper[6].startswith("3100 [")
    assert hopper[7] == "3100 ± 1581"
    assert hopper[8] == "2410 ± 10 (Hopper-v3)"  # rl-zoo: deterministic evaluation
    assert hopper[9] == "2609 ± 701 (Hopper-v3)"  # Tianshou: the best over its curve
    assert hopper[10] == "3303 [3090, 3376] (Hopper-v5)"  # the defaults' eval IQM
    assert hopper[11] == "10m00s" and hopper[12] == f"{BUDGET / 600:.0f}"
    # Time to CleanRL's mean: 3 of 5 seeds, the median of 8000, 6000, 5000 steps and of 252.5,
    # 222.5, 212.5 s since the job's start (3m42s).
    assert hopper[13:15] == ["6k (3/5)", "3m42s"]
    # Time to rl-zoo's 2410.435 on the eval return (evals at 5000 and 10000 steps, rising to
    # 1100 ... 5100): seed 4 at 5000 (2550), seeds 2 and 3 at 10000; seeds 0, 1 never. Their eval
    # rows' times: 12.5 + 5 x 40 + 2.25 = 214.75, 12.5 + 10 x 30 + 2.25 = 314.75, 12.5 + 10 x 35
    # + 2.25 = 364.75 s: the median 314.75 s (5m14s), of 10000 steps.
    assert hopper[15:] == ["10k (3/5)", "5m14s"]

    ant = row_of(md, "Ant-v5")  # seed 4 failed: 4 of its 5 jobs are its seeds
    assert ant[1] == "4 of 5"
    assert ant[2] == iqm_cell(TRAIN["ant"][:4])
    assert ant[4] == ""  # CleanRL has no Ant number at 1M steps
    assert ant[5] == "652 [455, 785] (Ant-v5)"
    assert ant[8] == "1327 ± 452 (Ant-v3)"
    assert ant[9] == "3258 ± 1079 (Ant-v3)"  # Tianshou
    assert ant[11] == "9m35s"  # the median of 500, 550, 600, 650 s
    assert ant[13:15] == ["—", "—"]  # no CleanRL number: no time to it
    # rl-zoo's 1327.158: seeds 2 (1600) and 3 (2600) at 10000 steps (at 5000: 800 and 1300),
    # 314.75 and 364.75 s: the median 339.75 s
    assert ant[15:] == ["10k (2/4)", "5m39s"]

    swimmer = row_of(md, "Swimmer-v5")  # rl-zoo's Swimmer-v3 only
    assert swimmer[4] == "" and swimmer[5] == "" and swimmer[10] == ""
    assert (swimmer[8], swimmer[9]) == ("282 ± 10 (Swimmer-v3)", "67 ± 99 (Swimmer-v3)")
    assert swimmer[13:] == ["—", "—", "not reached (0/5)", "—"]  # 180 < 281.561
    assert "**To CleanRL mean**: per seed, the first logged `train/episode_return` >= " in md
    assert "**To rl-zoo mean**: the same with the deterministic eval return" in md
    assert swimmer[2] == iqm_cell(TRAIN["swimmer"])

    # What each anchor is and where it comes from, under the table.
    assert "1. **CleanRL PPO**: `ppo_continuous_action.py`, MuJoCo v4, 1M env steps, 3 seeds" in md
    assert "docs/benchmark/ppo_continuous_action.md" in md
    assert "2. **rl-zoo PPO**: " in md and "rl-baselines3-zoo/blob/master/benchmark.md" in md
    assert "3. **Tianshou PPO**: " in md and "thu-ml/tianshou `examples/mujoco/README.md`" in md
    assert "4. **rlexp defaults**: " in md and "5. **rlexp defaults**: " in md
    assert "success" not in md.lower()  # Gymnasium tasks: no success anywhere

    with open(env_sweep / "results.csv") as f:
        table = {r["env"]: r for r in csv.DictReader(f)}
    assert list(table) == ["Hopper-v5", "Ant-v5", "Swimmer-v5"]
    h = table["Hopper-v5"]
    assert (h["n_seeds"], h["n_jobs"], h["seeds"]) == ("5", "5", "0 1 2 3 4")
    assert float(h["train_iqm"]) == 3000.0 and float(h["eval_iqm"]) == 3100.0
    assert float(h["train_mean"]) == 3000.0 and float(h["eval_std"]) == pytest.approx(1581.14, 1e-4)
    low, high = bootstrap_ci(np.array(TRAIN["hopper"]), iqm)
    assert (float(h["train_iqm_ci_low"]), float(h["train_iqm_ci_high"])) == (low, high)
    assert float(h["wall_median_s"]) == 600 and float(h["env_steps_per_s_median"]) == BUDGET / 600
    assert (h["cleanrl_ppo_env"], float(h["cleanrl_ppo_mean"])) == ("Hopper-v4", 2382.86)
    assert (h["rl_zoo_ppo_env"], float(h["rl_zoo_ppo_std"])) == ("Hopper-v3", 10.026)
    assert h["success_iqm"] == ""  # the task defines no success
    assert table["Ant-v5"]["cleanrl_ppo_mean"] == "" and table["Ant-v5"]["n_seeds"] == "4"
    assert (h["cleanrl_ppo_reached"], h["cleanrl_ppo_wall_n"]) == ("3", "3")
    assert float(h["cleanrl_ppo_steps_median"]) == 6000
    assert float(h["cleanrl_ppo_wall_median_s"]) == 222.5
    time_to = ("reached", "steps_median", "wall_median_s", "wall_n")
    assert [table["Ant-v5"][f"cleanrl_ppo_{k}"] for k in time_to] == ["", "", "", ""]
    assert [h[f"rl_zoo_ppo_{k}"] for k in time_to] == ["3", "10000", "314.75", "3"]
    ant_zoo = [float(table["Ant-v5"][f"rl_zoo_ppo_{k}"]) for k in time_to]
    assert ant_zoo == [2, 10000, 339.75, 2]
    assert [table["Swimmer-v5"][f"rl_zoo_ppo_{k}"] for k in time_to] == ["0", "", "", "0"]
    defaults = [h[f"rlexp_defaults_eval_{k}"] for k in ("env", "mean", "std", "ci_low", "ci_high")]
    assert defaults == ["Hopper-v5", "3303", "", "3090", "3376"]
    assert not (env_sweep / "results.png").exists()  # plot=False


def test_anchors_only_for_tasks_a_source_has_a_number_for():
    defaults = {"rlexp_defaults_train", "rlexp_defaults_eval"}
    assert set(anchors_for("Hopper-v5")) == {"cleanrl_ppo", "rl_zoo_ppo", "tianshou_ppo", *defaults}
    assert anchors_for("Walker2d-v5")["cleanrl_ppo"].mean == 2287.95
    assert anchors_for("HalfCheetah-v5")["cleanrl_ppo"].mean == 1442.64
    assert set(anchors_for("Ant-v5")) == {"rl_zoo_ppo", "tianshou_ppo", *defaults}
    assert anchors_for("HalfCheetah-v5")["rlexp_defaults_eval"].ci == (1769, 1883)
    assert anchors_for("Walker2d-v5")["rlexp_defaults_train"].mean == 3555
    swimmer = anchors_for("Swimmer-v5")  # rl-zoo's benchmark.md: ppo Swimmer-v3 281.561 9.671
    assert set(swimmer) == {"rl_zoo_ppo", "tianshou_ppo"} and swimmer["rl_zoo_ppo"].mean == 281.561
    assert anchors_for("push_cube") == {} and anchors_for("cart_pole") == {}
    # CleanRL's benchmark file (the same PR #424 runs): InvertedPendulum-v4, Humanoid-v4
    assert anchors_for("InvertedPendulum-v5")["cleanrl_ppo"].mean == 963.09
    assert set(anchors_for("Humanoid-v5")) == {"cleanrl_ppo", "tianshou_ppo"}
    # Tianshou's README, PPO "Tianshou (1M)": every task of the suite, v3 (v2: Reacher, pendulums)
    tianshou = {
        "Ant-v3": (3258.4, 1079.3), "HalfCheetah-v3": (5783.9, 1244.0),
        "Hopper-v3": (2609.3, 700.8), "Walker2d-v3": (3588.5, 756.6),
        "Swimmer-v3": (66.7, 99.1), "Humanoid-v3": (787.1, 193.5), "Reacher-v2": (-4.1, 0.3),
        "InvertedPendulum-v2": (1000.0, 0.0), "InvertedDoublePendulum-v2": (9231.3, 270.4),
    }  # fmt: skip
    for env_id, (mean, std) in tianshou.items():
        a = anchors_for(env_id.replace("-v3", "-v5").replace("-v2", "-v5"))["tianshou_ppo"]
        assert (a.env_id, a.mean, a.std) == (env_id, mean, std)
    assert set(anchors_for("Reacher-v5")) == {"tianshou_ppo"}
    assert anchors_for("Hopper") == anchors_for("Hopper-v4") and anchors_for(None) == {}


def test_a_sweep_over_envs_without_anchors_has_no_anchor_columns(tmp_path):
    multirun_yaml(tmp_path, ["env=reacher,cart_pole", "seed=0,1"])
    jobs = [("cart_pole", 0), ("cart_pole", 1), ("reacher", 0)]
    for num, (env, seed) in enumerate(jobs):
        write_job(tmp_path, num, [f"env={env}", f"seed={seed}"], 50.0 + seed, 60.0)
    md = report(tmp_path, plot=False)
    assert "## Results per env" in md
    assert row_of(md, "cart_pole")[1:4] == ["2", "50 [50, 51]", "50 ± 1"]
    assert row_of(md, "Reacher-v5")[1:3] == ["1", "50 [n/a, n/a]"]
    # Reacher has one anchor (Tianshou's eval number), cart_pole none: only that source's column
    assert "Tianshou PPO (1)" in md and "CleanRL" not in md and "rl-zoo" not in md
    assert "rlexp defaults (" not in md
    header = row_of(md.replace("| env |", "| `env` |", 1), "env")
    assert row_of(md, "cart_pole")[header.index("Tianshou PPO (1)")] == ""


def test_a_sweep_over_envs_no_source_has_a_number_for_has_no_anchor_columns(tmp_path):
    multirun_yaml(tmp_path, ["env=cart_pole", "seed=0,1"])
    for seed in range(2):
        write_job(tmp_path, seed, ["env=cart_pole", f"seed={seed}"], 50.0 + seed, 60.0)
    md = report(tmp_path, plot=False, results=True)
    assert "## Results per env" in md
    assert "CleanRL" not in md and "rl-zoo" not in md and "Tianshou" not in md
    assert "Anchors:" not in md and "defaults" not in md


def test_eval_success_is_shown_only_for_tasks_that_define_it(tmp_path):
    multirun_yaml(tmp_path, ["env=hopper,cart_pole", "seed=0,1,2"])
    num = 0
    for env in ("hopper", "cart_pole"):
        for seed in range(3):
            success = 0.0 if env == "hopper" else [0.5, 0.75, 1.0][seed]
            overrides = [f"env={env}", f"seed={seed}"]
            write_job(tmp_path, num, overrides, 100.0 * (seed + 1), 200.0, success=success)
            num += 1
    md = report(tmp_path, plot=False)
    assert "eval success: IQM [95% CI]" in md
    success = "eval success: IQM [95% CI]"
    assert cells_of(md, "Hopper-v5")[success] == "—"  # Gymnasium: no success, not a rate of 0
    x = np.array([0.5, 0.75, 1.0])
    low, high = bootstrap_ci(x, iqm)
    assert cells_of(md, "cart_pole")[success] == f"{float(iqm(x)):.2f} [{low:.2f}, {high:.2f}]"
    assert "Gymnasium's tasks have none" in md
    with open(tmp_path / "results.csv") as f:
        table = {r["env"]: r for r in csv.DictReader(f)}
    assert table["Hopper-v5"]["success_iqm"] == "" and table["Hopper-v5"]["success_n"] == ""
    assert float(table["cart_pole"]["success_iqm"]) == pytest.approx(0.75)


def test_a_sweep_not_over_envs_reads_as_before(tmp_path):
    multirun_yaml(tmp_path, ["env=hopper", "algorithm.lr=1,2", "seed=0,1"])
    for num in range(4):
        lr, seed = divmod(num, 2)
        overrides = ["env=hopper", f"algorithm.lr={lr + 1}", f"seed={seed}"]
        write_job(tmp_path, num, overrides, 100.0 * num, 200.0)
    md = report(tmp_path, plot=True)
    assert "Results per env" not in md and "CleanRL" not in md
    assert not (tmp_path / "results.csv").exists() and not (tmp_path / "results.png").exists()
    assert (tmp_path / "curves.png").exists()
    assert md == report(tmp_path, plot=False, results=False)


def test_the_results_view_on_one_env_and_its_figure_at_a_given_path(tmp_path):
    """``+sweep=mujoco_1m env=hopper``: one env, so the view is asked for; the figure goes where
    the docs want it (e.g. docs/results_1m.png) as well as into the sweep dir."""
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    multirun_yaml(sweep, ["env=hopper", "seed=0,1"])
    for seed in (0, 1):
        write_job(sweep, seed, ["env=hopper", f"seed={seed}"], 1000.0 + seed, 900.0)
    assert "Results per env" not in report(sweep, plot=False)
    target = tmp_path / "docs" / "results_1m.png"
    target.parent.mkdir()
    md = report(sweep, plot=False, results_plot=target)
    assert "## Results per env" in md and row_of(md, "Hopper-v5")[1] == "2"
    assert target.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (sweep / "results.png").exists()  # plot=False: only the figure asked for
    report(sweep, results=True)
    assert (sweep / "results.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_results_png_draws_each_envs_bands_and_its_anchors(env_sweep, monkeypatch):
    import matplotlib.axes

    bands, lines = [], []
    real_fill, real_axhline = matplotlib.axes.Axes.fill_between, matplotlib.axes.Axes.axhline

    def fill(self, x, y1, y2, **kw):
        bands.append((self, np.asarray(x), np.asarray(y1), np.asarray(y2)))
        return real_fill(self, x, y1, y2, **kw)

    def axhline(self, y=0, **kw):
        lines.append((self, y, kw.get("label")))
        return real_axhline(self, y, **kw)

    monkeypatch.setattr(matplotlib.axes.Axes, "fill_between", fill)
    monkeypatch.setattr(matplotlib.axes.Axes, "axhline", axhline)
    report(env_sweep)
    assert (env_sweep / "results.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    results_bands = [b for b in bands if not b[0].get_title().startswith("IQM")]  # not curves.png
    assert [b[0].get_title() for b in results_bands] == [
        *("Hopper-v5", "Hopper-v5", "Ant-v5", "Ant-v5", "Swimmer-v5", "Swimmer-v5")
    ]
    hopper_train, hopper_eval = results_bands[0], results_bands[1]
    assert list(hopper_train[1]) == list(range(BATCH, BUDGET + 1, BATCH))
    assert list(hopper_eval[1]) == [EVAL_EVERY, BUDGET]
    # At the last step each band is the table's interval of that metric.
    low, high = bootstrap_ci(np.array(TRAIN["hopper"]), iqm)
    assert (hopper_train[2][-1], hopper_train[3][-1]) == pytest.approx((low, high))
    low, high = bootstrap_ci(np.array(EVAL["hopper"]), iqm)
    assert (hopper_eval[2][-1], hopper_eval[3][-1]) == pytest.approx((low, high))
    drawn = {(ax.get_title(), y) for ax, y, _ in lines}
    assert drawn == {
        *(
            ("Hopper-v5", 2382.86),
            ("Hopper-v5", 2410.435),
            ("Hopper-v5", 2609.3),
            ("Hopper-v5", 2504),
            ("Hopper-v5", 3303),
        ),
        *(("Ant-v5", 1327.158), ("Ant-v5", 3258.4), ("Ant-v5", 652), ("Ant-v5", 1112)),
        *(("Swimmer-v5", 281.561), ("Swimmer-v5", 66.7)),
    }


def test_rlexp_report_on_a_sweep_over_envs_prints_the_results(env_sweep):
    proc = rlexp_report(str(env_sweep), "--no-plot")
    assert proc.returncode == 0, proc.stderr
    assert "## Results per env" in proc.stdout
    assert row_of(proc.stdout, "Hopper-v5")[4] == "2383 ± 272 (Hopper-v4)"
    assert (env_sweep / "results.csv").exists()


def test_rlexp_report_results_flags_on_one_env(tmp_path):
    """``--results`` asks for the view on a one-env sweep; ``--results-plot`` writes the figure
    where it is asked (even with ``--no-plot``)."""
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    multirun_yaml(sweep, ["env=hopper", "seed=0,1"])
    for seed in (0, 1):
        write_job(sweep, seed, ["env=hopper", f"seed={seed}"], 1000.0 + seed, 900.0)
    plain = rlexp_report(str(sweep), "--no-plot")
    assert plain.returncode == 0, plain.stderr
    assert "Results per env" not in plain.stdout
    asked = rlexp_report(str(sweep), "--no-plot", "--results")
    assert asked.returncode == 0, asked.stderr
    assert "## Results per env" in asked.stdout and row_of(asked.stdout, "Hopper-v5")[1] == "2"
    target = tmp_path / "results_1m.png"
    drawn = rlexp_report(str(sweep), "--no-plot", "--results-plot", str(target))
    assert drawn.returncode == 0, drawn.stderr
    assert target.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_time_to_cleanrl_per_seed_from_the_jobs_start(env_sweep):
    """Per seed the first training row >= the anchor's mean: its step and its own ``time`` less
    the job's start (start-up included), not the time of a later row at that step (the eval's)."""
    hopper, ant, swimmer = results_of(env_sweep)
    t = hopper.to_cleanrl
    assert (t.target, t.n, t.k) == (2382.86, 5, 3)
    assert t.steps == HOPPER_REACHED and t.seconds == HOPPER_REACHED_S
    assert (t.median_steps, t.median_s) == (6000, 222.5)
    assert ant.to_cleanrl is None and swimmer.to_cleanrl is None


def test_time_to_cleanrl_not_reached_and_envs_without_an_anchor(tmp_path):
    multirun_yaml(tmp_path, ["env=hopper,swimmer", "seed=0,1,2"])
    num = 0
    for env, finals in (("hopper", [1000.0, 2000.0, 2382.0]), ("swimmer", [50.0, 60.0, 70.0])):
        for seed, train in enumerate(finals):
            write_job(tmp_path, num, [f"env={env}", f"seed={seed}"], train, 100.0)
            num += 1
    md = report(tmp_path, plot=False)
    steps, wall = "steps to CleanRL mean (median, seeds)", "wall to CleanRL mean (median)"
    hopper, swimmer = cells_of(md, "Hopper-v5"), cells_of(md, "Swimmer-v5")
    assert (hopper[steps], hopper[wall]) == ("not reached (0/3)", "—")  # 2382 < 2382.86
    assert (swimmer[steps], swimmer[wall]) == ("—", "—")
    with open(tmp_path / "results.csv") as f:
        table = {r["env"]: r for r in csv.DictReader(f)}
    time_to = ("reached", "steps_median", "wall_median_s", "wall_n")
    assert [table["Hopper-v5"][f"cleanrl_ppo_{k}"] for k in time_to] == ["0", "", "", "0"]
    assert [table["Swimmer-v5"][f"cleanrl_ppo_{k}"] for k in time_to] == ["", "", "", ""]


def test_time_to_cleanrl_leaves_out_the_time_of_resumed_jobs_and_rows_without_one(tmp_path):
    """Seed 1 was resumed (its start is its last attempt's, after its first rows): its step counts,
    its time does not; seed 2's rows have no ``time``; the time is the median of seeds 0 and 3."""
    multirun_yaml(tmp_path, ["env=hopper", "seed=0,1,2,3"])
    kwargs = [{"batch_s": 30.0}, {"start_s": 120}, {"times": False}, {"batch_s": 20.0}]
    for seed, kw in enumerate(kwargs):  # 5000 at the end: 2382.86 reached at step 5000
        write_job(tmp_path, seed, ["env=hopper", f"seed={seed}"], 5000.0, 100.0, **kw)
    (r,) = results_of(tmp_path)
    assert r.to_cleanrl.steps == [5000] * 4
    assert r.to_cleanrl.seconds == [STARTUP_S + 5 * 30.0, STARTUP_S + 5 * 20.0]
    assert r.jobs[1].wall_s == 600 - 120  # the wall per job: also its last attempt
    md = report(tmp_path, plot=False, results=True)
    cells = cells_of(md, "Hopper-v5")
    assert cells["steps to CleanRL mean (median, seeds)"] == "5k (4/4)"
    assert cells["wall to CleanRL mean (median)"] == "2m17s (2 of 4 seeds)"  # 137.5 s
    with open(tmp_path / "results.csv") as f:
        (row,) = csv.DictReader(f)
    assert (row["cleanrl_ppo_reached"], row["cleanrl_ppo_wall_n"]) == ("4", "2")
    assert float(row["cleanrl_ppo_wall_median_s"]) == 137.5


def test_a_job_still_training_is_not_called_dead(tmp_path):
    """``rlexp report`` during a sweep: a ``running`` job with a fresh heartbeat from a live process
    is still running; one whose process is gone died (the heartbeat and PID rule of rlexp runs)."""
    import os
    import socket
    import time

    from rlexp.analysis.reporting.jobs import read_job

    multirun_yaml(tmp_path, ["env=hopper", "seed=0,1"])
    live = write_job(tmp_path, 0, ["env=hopper", "seed=0"], 1.0, 1.0, state="running")
    dead = write_job(tmp_path, 1, ["env=hopper", "seed=1"], 1.0, 1.0, state="running")
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    for job_dir, pid in ((live, os.getpid()), (dead, int(gone.stdout))):
        beat = {"host": socket.gethostname(), "pid": pid, "time": time.time(), "interval_s": 10.0}
        (job_dir / "heartbeat.json").write_text(json.dumps(beat))
        status = json.loads((job_dir / "status.json").read_text())
        (job_dir / "status.json").write_text(json.dumps({**status, "pid": pid}))
    assert read_job(live, None).why.startswith("still running")
    assert read_job(dead, None).why.startswith("died: ")
    assert "still running" in report(tmp_path, plot=False)
