"""``rlexp report`` on sweep dirs it must survive: files of the wrong shape (a torn or foreign
``metrics.jsonl`` line, a ``status.json`` that is not an object), jobs that never started, a sweep
dir it cannot write into, and bad arguments. Real sweeps with failing jobs: tests/test_sweeps.py."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from conftest import REPO

BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"


def rlexp_report(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rlexp.cli", "report", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(REPO / "src")},
    )


def multirun_yaml(sweep: Path, task: list[str], sweeper: dict | None = None) -> None:
    """The parts of Hydra's ``multirun.yaml`` that say which jobs a sweep launches."""
    cfg = {
        "hydra": {
            "sweep": {"dir": str(sweep), "subdir": "${hydra.job.num}"},
            "sweeper": sweeper
            or {"_target_": BASIC_SWEEPER, "max_batch_size": None, "params": None},
            "overrides": {"task": task},
        }
    }
    (sweep / "multirun.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(cfg)))


def job(sweep: Path, num: int, overrides: list[str], status=None, metrics: str | None = None):
    """A job dir as a sweep leaves it; ``status``/``metrics`` are written as given (any shape)."""
    d = sweep / str(num)
    (d / ".hydra").mkdir(parents=True)
    (d / ".hydra/overrides.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(overrides)))
    if status is not None:
        (d / "status.json").write_text(status if isinstance(status, str) else json.dumps(status))
    if metrics is not None:
        (d / "metrics.jsonl").write_text(metrics)
    return d


def rows(*rows: dict) -> str:
    return "".join(json.dumps(r) + "\n" for r in rows)


def finished(step: int = 512) -> dict:
    return {"state": "finished", "global_step": step, "final_eval": {}}


def test_metrics_lines_of_the_wrong_shape_are_skipped_and_named(tmp_path):
    from rlexp.analysis.report import find_jobs, report

    metrics = (
        rows(
            {"step": 256, "eval/episode_return": 10.0, "perf/collect_time": 1.0},
            [1, 2, 3],  # a JSON array, not an object
            "just a string",
            {"eval/episode_return": 99.0},  # no step
            {"step": "512", "eval/episode_return": 98.0},  # a step that is a string
            {"step": True, "eval/episode_return": 97.0},  # a step that is a boolean
            {"step": 384, "eval/episode_return": "high"},  # a metric that is a string
            {"step": 448, "eval/episode_return": [1.0]},  # a metric that is a list
            {"step": 480, "perf/collect_time": "slow", "perf/update_time": 0.5},
            {"step": 512, "eval/episode_return": 20.0},
        )
        + '{"step": 640, "eval/episode_re'
    )  # torn by a kill
    job(tmp_path, 0, ["seed=0"], finished(), metrics)
    job(tmp_path, 1, ["seed=1"], finished(), rows({"step": 512, "eval/episode_return": 30.0}))
    multirun_yaml(tmp_path, ["seed=0,1"])

    (j0, j1) = find_jobs(tmp_path)
    assert j0.curve == [(256, 10.0), (512, 20.0)] and j1.curve == [(512, 30.0)]
    assert j0.time_s == pytest.approx(1.5)  # step 256: 1.0; step 480: the number, not "slow"
    md = report(tmp_path, plot=True)
    assert "2 jobs expected" in md and "2 finished" in md
    assert "## Files read in part (1)" in md
    assert (
        "- `0/metrics.jsonl`: 9 line(s) skipped (first: line 2, a JSON array, not an object)" in md
    )
    assert (tmp_path / "curves.png").stat().st_size > 0


def test_status_json_of_the_wrong_shape_is_an_unfinished_job_with_the_reason(tmp_path):
    from rlexp.analysis.report import report

    good = rows({"step": 512, "eval/episode_return": 5.0})
    job(tmp_path, 0, ["seed=0"], finished(), good)
    job(tmp_path, 1, ["seed=1"], "[1, 2]", good)  # a list
    job(tmp_path, 2, ["seed=2"], '"finished"', good)  # a string
    job(tmp_path, 3, ["seed=3"], {"state": "finished", "global_step": "lots"}, good)
    job(tmp_path, 4, ["seed=4"], {"state": 7, "global_step": 512}, good)
    job(tmp_path, 5, ["seed=5"], '{"state": "runn', good)  # torn
    job(tmp_path, 6, ["seed=6"], {"state": "failed", "reason": ["a", "list"]}, "")
    multirun_yaml(tmp_path, ["seed=range(7)"])

    md = report(tmp_path, plot=False)
    assert "7 jobs expected" in md and "2 finished" in md and "5 failed or unfinished" in md
    lines = md.splitlines()

    def row(job_dir: str) -> str:
        return next(ln for ln in lines if ln.startswith(f"| `{job_dir}` |"))

    assert "| unreadable | 512 | status.json: a JSON array, not an object |" in row("1")
    assert "| unreadable | 512 | status.json: a JSON string, not an object |" in row("2")
    assert "| unreadable | 512 | status.json: state 7 is not a string |" in row("4")
    assert "| unreadable | 512 | status.json: not JSON |" in row("5")
    assert '| failed | 0 | ["a", "list"] |' in row("6")
    # global_step "lots": the job counts as finished at its last logged step, and the file is named.
    assert not any(ln.startswith("| `3` |") for ln in lines)
    assert "- `3/status.json`: global_step 'lots' is not a number" in md


def test_other_files_of_the_wrong_shape(tmp_path):
    from rlexp.analysis.report import report

    d = job(tmp_path, 0, ["seed=0"], finished())
    (d / "metrics.jsonl").write_bytes(b"\xff\xfe\x00garbage\n")  # not UTF-8 at all
    d = job(tmp_path, 1, ["seed=1"], finished(), rows({"step": 512, "eval/episode_return": 1.0}))
    (d / ".hydra/overrides.yaml").write_text("seed: [unclosed\n")
    (tmp_path / "multirun.yaml").write_text("- not\n- a mapping\n")

    md = report(tmp_path, plot=False)
    assert (
        "2 jobs (how many the sweep was to run is not known: multirun.yaml is not a mapping)" in md
    )
    assert "- `1/.hydra/overrides.yaml`: not readable" in md
    assert "- `0/metrics.jsonl`: 1 line(s) skipped (first: line 1, not JSON" in md


def test_jobs_expected_from_multirun_yaml_but_never_started_are_listed(tmp_path):
    from rlexp.analysis.report import report

    # The grid as Hydra expands it: a sweeper preset's params, then the command line (which wins).
    sweeper = {
        "_target_": BASIC_SWEEPER,
        "max_batch_size": None,
        "params": {"seed": "0,1", "algorithm.lr": "1,2"},
    }
    multirun_yaml(tmp_path, ["algorithm.lr=3,4,5", "env=hopper"], sweeper)
    good = rows({"step": 512, "eval/episode_return": 1.0})
    job(tmp_path, 0, ["seed=0", "algorithm.lr=3", "env=hopper"], finished(), good)
    job(tmp_path, 4, ["seed=1", "algorithm.lr=4", "env=hopper"], finished(), good)
    job(tmp_path, 9, ["seed=0", "algorithm.lr=9", "env=hopper"], finished(), good)  # an older sweep

    md = report(tmp_path, plot=False)
    assert "6 jobs expected (multirun.yaml: the grid of the sweep's overrides), 2 started" in md
    assert (
        "4 never started" in md and "1 job dir(s) are not among the jobs multirun.yaml lists" in md
    )
    assert "## Never started (4)" in md
    for num, seed, lr in [(1, 0, 4), (2, 0, 5), (3, 1, 3), (5, 1, 5)]:
        assert f"| #{num} | `seed={seed} algorithm.lr={lr} env=hopper` |" in md
    assert "| #0 |" not in md and "| #4 |" not in md


def test_a_glob_over_a_config_group_is_expanded_with_rlexp_configs(tmp_path):
    from rlexp.analysis.report import report

    multirun_yaml(tmp_path, ["env=glob(inverted_*)", "seed=0"])
    job(tmp_path, 0, ["env=inverted_double_pendulum", "seed=0"], finished(), "")
    md = report(tmp_path, plot=False)
    assert "2 jobs expected (multirun.yaml: the grid of the sweep's overrides), 1 started" in md
    assert "| #1 | `env=inverted_pendulum seed=0` |" in md


def test_optuna_trials_that_never_started(tmp_path):
    from rlexp.analysis.report import report

    sweeper = {"_target_": "hydra_plugins.hydra_optuna_sweeper.optuna_sweeper.OptunaSweeper"}
    multirun_yaml(tmp_path, ["env=hopper"], {**sweeper, "n_trials": 3})
    job(tmp_path, 0, ["algorithm.lr=0.1", "env=hopper"], finished(), "")
    md = report(tmp_path, plot=False)
    assert "3 jobs expected (multirun.yaml: hydra.sweeper.n_trials), 1 started" in md
    assert "| #1 | `(chosen by the sweeper)` |" in md and "| #2 |" in md


def test_a_sweep_that_started_no_job_is_reported_from_multirun_yaml(tmp_path):
    multirun_yaml(tmp_path, ["seed=0,1"])
    proc = rlexp_report(str(tmp_path), "--no-plot")
    assert proc.returncode == 0, proc.stderr
    assert "2 jobs expected" in proc.stdout and "## Never started (2)" in proc.stdout


def _make_read_only(path: Path) -> bool:
    """chmod a-w; as root (which chmod does not stop) also chattr +i. True if writes now fail."""
    path.chmod(0o555)
    if os.geteuid() == 0 and shutil.which("chattr"):
        subprocess.run(["chattr", "+i", str(path)], capture_output=True)
    try:
        (path / ".probe").write_text("x")
    except OSError:
        return True
    (path / ".probe").unlink()
    return False


def _make_writable(path: Path) -> None:
    if os.geteuid() == 0 and shutil.which("chattr"):
        subprocess.run(["chattr", "-i", str(path)], capture_output=True)
    path.chmod(0o755)


def test_a_read_only_sweep_dir_prints_the_report_and_says_what_was_not_written(tmp_path):
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    job(sweep, 0, ["seed=0"], finished(), rows({"step": 512, "eval/episode_return": 3.0}))
    multirun_yaml(sweep, ["seed=0"])
    if not _make_read_only(sweep):
        _make_writable(sweep)
        pytest.skip("cannot make a dir read-only here (root without chattr)")
    try:
        proc = rlexp_report(str(sweep))
    finally:
        _make_writable(sweep)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"# Sweep report: `{sweep}`") and "1 finished" in proc.stdout
    problems = [ln for ln in proc.stderr.splitlines() if "could not" in ln]
    expected = f"rlexp report: could not write report.md, report.csv, curves.png into {sweep} ("
    assert len(problems) == 1 and problems[0].startswith(expected), proc.stderr
    assert "Traceback" not in proc.stderr
    assert not any((sweep / n).exists() for n in ("report.md", "report.csv", "curves.png"))


@pytest.mark.parametrize("what", ["missing", "a file", "no jobs", "no metric", "no dir"])
def test_bad_arguments_are_one_line_and_exit_2(tmp_path, what):
    target = tmp_path / "x"
    args = [str(target)]
    if what == "a file":
        target.write_text("hello")
    elif what == "no jobs":
        target.mkdir()
    elif what == "no metric":
        args = [str(tmp_path), "--metric"]
    elif what == "no dir":
        args = []
    proc = rlexp_report(*args)
    assert proc.returncode == 2
    assert proc.stdout == "" and len(proc.stderr.splitlines()) == 1, proc.stderr
    assert proc.stderr.startswith("rlexp report: ")
    if what in ("missing", "a file", "no jobs"):
        assert str(target) in proc.stderr


# Steps to threshold: the pure function on hand-made (step, value) sequences, then the report.

NAN = float("nan")


@pytest.mark.parametrize(
    "points, first, three",
    [
        pytest.param([(100, 500.0), (200, 480.0), (300, 490.0)], 100, 100, id="at-the-first-eval"),
        pytest.param(
            [(100, 10.0), (200, 480.0), (300, 20.0)], 200, None, id="reached-then-dropped"
        ),
        pytest.param(
            [(100, 480.0), (200, 490.0), (300, 100.0), (400, 476.0), (500, 475.0), (600, 500.0)],
            100,
            400,
            id="three-in-a-row-broken-by-a-dip-then-reached",
        ),
        pytest.param([(100, 10.0), (200, 474.9), (300, 20.0)], None, None, id="never-reached"),
        pytest.param([], None, None, id="no-values"),
        pytest.param(
            [(100, NAN), (200, 480.0), (300, None), (400, NAN), (500, 490.0), (600, 475.0)],
            200,
            200,
            id="nan-and-absent-values-skipped",
        ),
        pytest.param(
            [(300, 480.0), (100, 10.0), (500, 490.0), (200, 476.0), (400, 30.0), (600, 500.0)],
            200,
            None,
            id="unsorted-lines-sorted-by-step",
        ),
        pytest.param(
            [(100, 480.0), (200, 490.0), (300, 495.0), (200, 10.0)],
            100,
            None,
            id="a-re-logged-step-the-later-value-wins",
        ),
    ],
)
def test_steps_to_threshold(points, first, three):
    from rlexp.analysis.report import IN_A_ROW, steps_to_threshold

    assert IN_A_ROW == 3
    assert steps_to_threshold(points, 475.0) == first
    assert steps_to_threshold(points, 475.0, in_a_row=3) == three


def test_steps_to_threshold_refuses_an_empty_run():
    from rlexp.analysis.report import steps_to_threshold

    with pytest.raises(ValueError, match="in_a_row must be at least 1, got 0"):
        steps_to_threshold([(1, 1.0)], 0.0, in_a_row=0)


def test_reached_stats_leave_seeds_that_never_reached_out_and_count_them():
    from rlexp.analysis.report import reached_stats

    k, median, iqm = reached_stats([400, None, 100, 300, 200, None, 10_000, 250])
    assert k == 6 and median == 275.0
    assert iqm == pytest.approx((200 + 250 + 300 + 400) / 4)  # 6 values: the middle 4 (trim 1+1)
    k, median, iqm = reached_stats([None, None])
    assert k == 0 and median != median and iqm != iqm  # NaN: nothing to summarise


@pytest.mark.parametrize(
    "text, parsed",
    [
        ("475", (None, 475.0)),
        ("-12.5", (None, -12.5)),
        ("eval/success_rate=0.9", ("eval/success_rate", 0.9)),
        ("1e3", (None, 1000.0)),
    ],
)
def test_parse_threshold(text, parsed):
    from rlexp.analysis.report import parse_threshold

    assert parse_threshold(text) == parsed


@pytest.mark.parametrize("text", ["", "high", "nan", "inf", "=475", "eval/success_rate=", "a=b"])
def test_parse_threshold_refuses_what_is_not_a_finite_level(text):
    from rlexp.analysis.report import parse_threshold

    with pytest.raises(ValueError, match="is not VALUE or METRIC=VALUE with a finite number"):
        parse_threshold(text)


def grid_jobs(sweep: Path, task: list[str], curve_of) -> None:
    """A finished job dir for each job of the basic sweeper's grid over ``task`` (the overrides in
    the order Hydra writes them), and its multirun.yaml; ``curve_of(overrides)`` gives its rows."""
    from rlexp.analysis.report import plan_from_config

    multirun_yaml(sweep, task)
    plan = plan_from_config(OmegaConf.load(sweep / "multirun.yaml"))
    for expected in plan.jobs:
        overrides = list(expected.overrides)
        job(sweep, expected.num, overrides, finished(), rows(*curve_of(overrides)))


def test_a_sweep_over_config_group_choices_has_one_row_per_choice_with_seeds_pooled(tmp_path):
    from rlexp.analysis.report import find_jobs, report, summarize

    def curve(overrides: list[str]) -> list[dict]:
        seed = int(dict(o.split("=") for o in overrides)["seed"])
        final = (100.0 if "algorithm=ppo" in overrides else 50.0) + seed
        return [{"step": 512, "eval/episode_return": final}]

    grid_jobs(tmp_path, ["algorithm=ppo,grpo", "policy=mlp", "seed=0,1,2"], curve)
    assert (tmp_path / "5/.hydra/overrides.yaml").read_text().split() == [
        *("-", "algorithm=grpo", "-", "policy=mlp", "-", "seed=2")
    ]
    stats = {s.label: s for s in summarize(find_jobs(tmp_path))}
    assert sorted(stats) == ["algorithm=grpo", "algorithm=ppo"]
    assert [j.seed for j in stats["algorithm=ppo"].jobs] == ["0", "1", "2"]
    assert list(stats["algorithm=grpo"].finals) == [50.0, 51.0, 52.0]
    md = report(tmp_path, plot=False)
    assert "6 jobs expected" in md and "6 finished" in md and "Shared overrides: `policy=mlp`" in md
    assert "| `algorithm=ppo` | 3 | 101.00 ± 1.00 |" in md
    assert "| `algorithm=grpo` | 3 | 51.00 ± 1.00 |" in md

    # Two group choices varied at once: one row per (algorithm, policy), seeds still pooled.
    other = tmp_path / "two_groups"
    other.mkdir()
    grid_jobs(other, ["algorithm=ppo,grpo", "policy=mlp,actor_only", "seed=0,1"], curve)
    stats = {s.label: s for s in summarize(find_jobs(other))}
    assert sorted(stats) == [
        "algorithm=grpo policy=actor_only",
        "algorithm=grpo policy=mlp",
        "algorithm=ppo policy=actor_only",
        "algorithm=ppo policy=mlp",
    ]
    assert all([j.seed for j in s.jobs] == ["0", "1"] for s in stats.values())


def test_rlexp_report_threshold_counts_the_seeds_that_reached_it(tmp_path):
    import csv

    # ppo: seeds reach 475 at steps 200/300/100 (3 in a row from 200/300/300); seed 3 never does.
    # grpo: seed 0 reaches it once and drops (never 3 in a row); seed 1 never; seed 2 failed.
    returns = {
        ("ppo", 0): [10, 480, 490, 500, 500],
        ("ppo", 1): [10, 20, 480, 476, 490],
        ("ppo", 2): [476, 30, 480, 490, 495],
        ("ppo", 3): [10, 20, 30, 40, 50],
        ("grpo", 0): [10, 480, 20, float("nan"), 30],
        ("grpo", 1): [10, 20, 30, 40, 50],
        ("grpo", 2): [10, 480, 490, 500, 500],
    }
    for num, ((algo, seed), values) in enumerate(returns.items()):
        metrics = rows(
            *(
                {"step": 100 * (i + 1), "eval/episode_return": v, "eval/success_rate": v / 500}
                for i, v in enumerate(values)
            )
        ).replace("NaN", "null")
        status = finished() if (algo, seed) != ("grpo", 2) else {"state": "failed", "reason": "x"}
        job(tmp_path, num, [f"algorithm={algo}", f"seed={seed}"], status, metrics)
    multirun_yaml(tmp_path, ["algorithm=ppo,grpo", "seed=0,1,2,3"])

    proc = rlexp_report(str(tmp_path), "--threshold", "475", "--no-plot")
    assert proc.returncode == 0, proc.stderr
    md = (tmp_path / "report.md").read_text()
    assert proc.stdout == md
    assert "## Steps to threshold: `eval/episode_return` >= 475" in md
    assert (
        "| configuration | reached | median step | IQM step | reached (3 in a row) "
        "| median step (3 in a row) | IQM step (3 in a row) |"
    ) in md
    assert "| `algorithm=ppo` | 3/4 | 200 | 200 | 3/4 | 300 | 267 |" in md
    assert "| `algorithm=grpo` | 1/2 | 200 | 200 | 0/2 | n/a | n/a |" in md
    # The main table is the one without --threshold.
    assert "| `algorithm=ppo` | 4 | " in md and "| `algorithm=grpo` | 2 | " in md
    with open(tmp_path / "report.csv") as f:
        csv_rows = {r["configuration"]: r for r in csv.DictReader(f)}
    ppo = csv_rows["algorithm=ppo"]
    assert (ppo["threshold_metric"], ppo["threshold"]) == ("eval/episode_return", "475.0")
    assert (ppo["n_seeds"], ppo["n_reached"], ppo["n_reached_3_in_a_row"]) == ("4", "3", "3")
    assert ppo["seeds"] == "0 1 2 3" and ppo["steps_to_threshold_per_seed"] == "200 300 100 none"
    assert ppo["steps_to_threshold_3_in_a_row_per_seed"] == "200 300 300 none"
    assert float(ppo["steps_to_threshold_median"]) == 200.0
    assert float(ppo["steps_to_threshold_3_in_a_row_iqm"]) == pytest.approx(800 / 3)
    grpo = csv_rows["algorithm=grpo"]
    assert grpo["steps_to_threshold_3_in_a_row_median"] == "nan"

    # METRIC=VALUE: the threshold in another metric than the score's.
    proc = rlexp_report(str(tmp_path), "--threshold", "eval/success_rate=0.96", "--no-plot")
    assert proc.returncode == 0, proc.stderr
    assert "## Steps to threshold: `eval/success_rate` >= 0.96" in proc.stdout
    # success rate 0.96 = return 480: ppo seed 1 dips to 476 after its first 480 (not 3 in a row)
    assert "| `algorithm=ppo` | 3/4 | 300 | 267 | 2/4 | 250 | 250 |" in proc.stdout


def test_no_threshold_leaves_the_report_as_it_was(tmp_path):
    from rlexp.analysis.report import CSV_FIELDS, report

    job(tmp_path, 0, ["seed=0"], finished(), rows({"step": 512, "eval/episode_return": 500.0}))
    multirun_yaml(tmp_path, ["seed=0"])
    md = report(tmp_path, plot=False)
    assert "Steps to threshold" not in md
    header = (tmp_path / "report.csv").read_text().splitlines()[0]
    assert header == ",".join(CSV_FIELDS)


@pytest.mark.parametrize("value", ["high", "eval/success_rate=", "nan"])
def test_a_bad_threshold_is_one_line_and_exit_2(tmp_path, value):
    proc = rlexp_report(str(tmp_path), "--threshold", value)
    assert proc.returncode == 2 and proc.stdout == ""
    assert len(proc.stderr.splitlines()) == 1, proc.stderr
    assert proc.stderr.startswith("rlexp report: argument --threshold")
    assert "is not VALUE or METRIC=VALUE" in proc.stderr


# Jobs a hook stopped early (status stopped_early): results, not failures; the budget they saved.

MEDIAN_REASON = (
    "median stopping rule: eval/episode_return=12 at step {step} is below the median 150 of 2 "
    "sibling jobs (hooks.median_stop)"
)


def stopped_early(step: int) -> dict:
    return {
        "state": "stopped_early",
        "global_step": step,
        "final_eval": {"eval/episode_return": 12.0},
        "reason": MEDIAN_REASON.format(step=step),
    }


def budget_config(job_dir: Path, where: str = "config.yaml", **trainer) -> None:
    """The trainer part of the config a job dir holds (rlexp's ``config.yaml`` or Hydra's)."""
    cfg = {"seed": 0, "trainer": {"iterations": None, "frames_per_batch": 1024, **trainer}}
    (job_dir / where).write_text(OmegaConf.to_yaml(OmegaConf.create(cfg)))


def curve(*values: float, every: int = 1024) -> str:
    return rows(
        *({"step": every * (i + 1), "eval/episode_return": v} for i, v in enumerate(values))
    )


@pytest.fixture
def median_sweep(tmp_path) -> Path:
    """lr=1 seeds 0,1 finished (budget 8192); lr=0 seed 0 stopped at 2048 and seed 1 at 4096;
    lr=2 seed 0 failed, seed 1 stopped early (its budget: iterations 4 x 1024 in .hydra/)."""
    multirun_yaml(tmp_path, ["algorithm.lr=1,0,2", "seed=0,1"])
    specs = [
        (["algorithm.lr=1", "seed=0"], finished(8192), curve(50, 150, 300, 400, every=2048)),
        (["algorithm.lr=1", "seed=1"], finished(8192), curve(40, 160, 310, 420, every=2048)),
        (["algorithm.lr=0", "seed=0"], stopped_early(2048), curve(10, 12)),
        (["algorithm.lr=0", "seed=1"], stopped_early(4096), curve(11, 14, 13, 16)),
        (["algorithm.lr=2", "seed=0"], {"state": "failed", "reason": "NaN loss"}, curve(5)),
        (["algorithm.lr=2", "seed=1"], stopped_early(2048), curve(20, 30)),
    ]
    for num, (overrides, status, metrics) in enumerate(specs):
        d = job(tmp_path, num, overrides, status, metrics)
        if num == 5:
            budget_config(d, ".hydra/config.yaml", iterations=4, total_frames=10**6)
        else:
            budget_config(d, total_frames=8192)
    return tmp_path


def test_jobs_stopped_early_are_results_listed_apart_with_the_budget_they_saved(median_sweep):
    import csv

    from rlexp.analysis.report import budget_saved, find_jobs, report

    jobs = find_jobs(median_sweep)
    assert [j.budget for j in jobs] == [8192] * 5 + [4096]
    assert [j.saved for j in jobs] == [0, 0, 8192 - 2048, 8192 - 4096, 0, 4096 - 2048]
    saved = budget_saved(jobs)
    assert (saved.saved, saved.total, saved.n_unknown) == (6144 + 4096 + 2048, 5 * 8192 + 4096, 0)

    md = report(median_sweep, plot=True)
    assert (
        "6 jobs expected (multirun.yaml: the grid of the sweep's overrides), 6 started, "
        "2 finished, 3 stopped early, 1 failed or unfinished, 0 never started."
    ) in md
    # Their value at the stop is their score; the configuration row counts them.
    assert "| unfinished | stopped early |" in md
    assert "| `algorithm.lr=1` | 2 | 410.00 ± 14.14 |" in md and md.count("| 0 | 0 |\n") == 1
    assert "| `algorithm.lr=0` | 2 | 14.00 ± 2.83 |" in md and "| 0 | 2 |\n" in md
    assert "| `algorithm.lr=2` | 1 | 30.00 ± 0.00 |" in md and "| 1 | 1 |\n" in md
    assert "## Stopped early (3)" in md
    reason = MEDIAN_REASON.format(step=2048)
    assert f"| `2` | `algorithm.lr=0 seed=0` | 2048 | 8192 | 12.00 | {reason} |" in md
    assert "| `3` | `algorithm.lr=0 seed=1` | 4096 | 8192 | 16.00 |" in md
    assert "| `5` | `algorithm.lr=2 seed=1` | 2048 | 4096 | 30.00 |" in md
    assert "Budget saved: 12288 env steps, 27.3% of the sweep's 45056" in md
    # The failed job is apart, and the stopped ones are not among the failures.
    assert "## Unfinished or failed jobs (1)" in md and "| `4` | `algorithm.lr=2 seed=0` |" in md
    failures = md.split("## Unfinished or failed jobs")[1]
    assert "stopped_early" not in failures and "median stopping rule" not in failures
    assert md.index("## Stopped early") < md.index("## Unfinished or failed jobs")
    with open(median_sweep / "report.csv") as f:
        table = {r["configuration"]: r for r in csv.DictReader(f)}
    lr0 = table["algorithm.lr=0"]
    assert (lr0["n_seeds"], lr0["seeds"], lr0["n_unfinished"]) == ("2", "0 1", "0")
    assert (lr0["n_stopped_early"], lr0["seeds_stopped_early"]) == ("2", "0 1")
    assert float(lr0["steps"]) == 3072  # the steps they reached
    lr2 = table["algorithm.lr=2"]
    assert (lr2["n_seeds"], lr2["n_unfinished"], lr2["n_stopped_early"]) == ("1", "1", "1")
    assert (median_sweep / "curves.png").stat().st_size > 0


def test_the_budget_of_a_job_stopped_early_without_a_readable_config_is_not_counted(tmp_path):
    from rlexp.analysis.report import report

    multirun_yaml(tmp_path, ["seed=0,1,2"])
    budget_config(job(tmp_path, 0, ["seed=0"], finished(8192), curve(100)), total_frames=8192)
    job(tmp_path, 1, ["seed=1"], stopped_early(2048), curve(12, 12))  # no config at all
    d = job(tmp_path, 2, ["seed=2"], stopped_early(1024), curve(12))
    (d / "config.yaml").write_text("trainer: [unclosed\n")
    md = report(tmp_path, plot=False)
    assert "| `1` | `seed=1` | 2048 | n/a | 12.00 |" in md
    assert (
        "Budget saved: 0 env steps, 0.0% of the sweep's 8192 (2 job dir(s) without a readable "
        "budget not counted)"
    ) in md
    assert "2 job(s) stopped early have no readable budget (config.yaml): not counted." in md
    assert "- `2/config.yaml`: not readable" in md


def test_a_job_stopped_early_before_any_eval_counts_as_stopped_not_as_a_seed(tmp_path):
    from rlexp.analysis.report import find_jobs, report, summarize

    multirun_yaml(tmp_path, ["seed=0,1"])
    job(tmp_path, 0, ["seed=0"], finished(), curve(100))
    stopped = {**stopped_early(256), "reason": "train/loss=0.1 <= 0.5 at step 256 (hooks.stop)"}
    job(tmp_path, 1, ["seed=1"], stopped, "")  # stopped on a training metric, no eval logged
    (s,) = summarize(find_jobs(tmp_path))
    assert (len(s.finals), s.n_unfinished, s.n_stopped_early) == (1, 0, 1)
    md = report(tmp_path, plot=False)
    assert (
        "| `1` | `seed=1` | 256 | n/a | n/a | train/loss=0.1 <= 0.5 at step 256 (hooks.stop) |"
        in md
    )
    assert "## Unfinished or failed jobs (0)" in md


def test_a_sweep_without_jobs_stopped_early_reads_as_before(tmp_path):
    from rlexp.analysis.report import report

    multirun_yaml(tmp_path, ["seed=0,1"])
    for num in (0, 1):
        budget_config(job(tmp_path, num, [f"seed={num}"], finished(), curve(5)), total_frames=512)
    md = report(tmp_path, plot=False)
    assert "stopped early" not in md.lower() and "Budget saved" not in md
    assert (
        "| configuration | seeds | final mean ± std | IQM [95% CI] | steps | time (s) | unfinished |\n"
        in md
    )


def test_the_sweep_summary_counts_jobs_stopped_early_as_done(median_sweep):
    from rlexp.launch.sweep import summarize_sweep

    config = OmegaConf.load(median_sweep / "multirun.yaml")
    line, ok = summarize_sweep(median_sweep, config)
    assert not ok  # job 4 failed
    assert line.startswith(
        f"sweep {median_sweep}: 5 of 6 jobs done: 2 finished, 3 stopped early: "
        f"{median_sweep / '2'} ({MEDIAN_REASON.format(step=2048)}), {median_sweep / '3'} ("
    )
    assert "; budget saved: 12288 env steps, 27.3% of the sweep's 45056; " in line
    assert line.endswith(
        f"; 1 failed: {median_sweep / '4'} (NaN loss) (rlexp report {median_sweep})"
    )

    # Had job 4 finished, every job would be done: the sweep exits 0.
    (median_sweep / "4/status.json").write_text(json.dumps(finished(8192)))
    line, ok = summarize_sweep(median_sweep, config)
    assert ok and line.startswith(f"sweep {median_sweep}: 6 of 6 jobs done: 3 finished, 3 stopped")
    assert line.endswith("budget saved: 12288 env steps, 27.3% of the sweep's 45056")
