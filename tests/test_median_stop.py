"""The median stopping rule end to end: ``python train.py -m hooks=median_stop algorithm.lr=3e-4,0
seed=0,1`` on InvertedPendulum. The grid runs the two learning jobs first (basic launcher: one after
another), so the two jobs that cannot learn (lr=0) find finished siblings, fall below their median
after the warm-up and stop early; the sweep exits 0 and ``rlexp report`` lists them with the budget
they saved. Synthetic sweep dirs: tests/test_report.py.

Why this budget: at 8192 env steps (the first eval past the warm-up, a quarter of 24576) PPO with
lr=3e-4 scores about 350-400 on InvertedPendulum-v5 (5 eval episodes; 1000 from ~12k steps on),
lr=0 about 25 (the untrained policy): a margin of more than 10x, so the stop does not hinge on a
lucky seed. Each lr=0 job that is not stopped at 8192 would be at a later eval."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO, run_train

BUDGET = 24576
MEDIAN_SWEEP = [
    "-m",
    "hooks=median_stop",
    "algorithm.lr=3e-4,0",
    "seed=0,1",
    "env=inverted_pendulum",
    f"trainer.total_frames={BUDGET}",
    "trainer.frames_per_batch=1024",
    "trainer.eval_every=4096",
    "trainer.eval_episodes=5",
    "trainer.save_every=100000",  # checkpoints: the final one (and best.pt) only
    "logger=none",
]
LEARNS, STILL = ("0", "1"), ("2", "3")  # job dirs: lr=3e-4 seeds 0,1; lr=0 seeds 0,1


def status(job: Path) -> dict:
    return json.loads((job / "status.json").read_text())


def evals(job: Path) -> list[tuple[int, float]]:
    rows = [json.loads(line) for line in (job / "metrics.jsonl").read_text().splitlines()]
    return [(r["step"], r["eval/episode_return"]) for r in rows if "eval/episode_return" in r]


def check_median_sweep(sweep: Path, proc: subprocess.CompletedProcess) -> None:
    """The two lr=0 jobs stopped early by the median rule, with a checkpoint at the stop; the two
    others finished; the summary line counts all four as done."""
    from rlexp.checkpoints.files import checkpoint_path, latest_checkpoint

    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    for name in LEARNS:
        s = status(sweep / name)
        assert (s["state"], s["global_step"]) == ("finished", BUDGET), (name, s)
    for name in STILL:
        job, s = sweep / name, status(sweep / name)
        assert s["state"] == "stopped_early", (name, s, evals(job))
        step = s["global_step"]
        assert BUDGET // 4 <= step < BUDGET, (name, step)
        assert s["reason"].startswith("median stopping rule: eval/episode_return=")
        assert f"at step {step} is below the median " in s["reason"]
        assert s["reason"].endswith(" sibling jobs (hooks.median_stop)")
        assert evals(job)[-1][0] == step  # stopped at the eval that decided it
        # The final checkpoint is the one at the stop.
        ckpt = latest_checkpoint(job / "checkpoints")
        assert ckpt == checkpoint_path(job / "checkpoints", "InvertedPendulum-v5_ppo", step)
    line = next(ln for ln in out.splitlines() if f"sweep {sweep}: " in ln)
    assert f"sweep {sweep}: 4 of 4 jobs done: 2 finished, 2 stopped early: {sweep / '2'} (" in line
    assert "failed" not in line and "(rlexp report" not in line
    saved = sum(BUDGET - status(sweep / n)["global_step"] for n in STILL)
    assert f"budget saved: {saved} env steps, {100 * saved / (4 * BUDGET):.1f}% of the" in line


def check_report(sweep: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "rlexp.cli", "report", str(sweep), "--no-plot"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(REPO / "src")},
    )
    assert proc.returncode == 0, proc.stderr
    md = proc.stdout
    assert "4 started, 2 finished, 2 stopped early, 0 failed or unfinished, 0 never started" in md
    assert "## Stopped early (2)" in md and "## Unfinished or failed jobs (0)" in md
    for name in STILL:
        s = status(sweep / name)
        assert f"| `{name}` | `hooks=median_stop algorithm.lr=0 seed=" in md
        assert f"| {s['global_step']} | {BUDGET} | " in md and s["reason"] in md
    saved = sum(BUDGET - status(sweep / n)["global_step"] for n in STILL)
    assert (
        f"Budget saved: {saved} env steps, {100 * saved / (4 * BUDGET):.1f}% of the sweep's " in md
    )
    # Both configurations keep their two seeds; the lr=0 row counts its two early stops.
    table = {ln.split(" | ")[0]: ln for ln in md.splitlines() if ln.startswith("| `algorithm.lr=")}
    assert sorted(table) == ["| `algorithm.lr=0.0003`", "| `algorithm.lr=0`"]
    assert table["| `algorithm.lr=0`"].startswith("| `algorithm.lr=0` | 2 | ")
    assert table["| `algorithm.lr=0`"].endswith(" | 0 | 2 |")
    assert table["| `algorithm.lr=0.0003`"].startswith("| `algorithm.lr=0.0003` | 2 | ")
    assert table["| `algorithm.lr=0.0003`"].endswith(" | 0 | 0 |")


@pytest.fixture(scope="module")
def median_sweep(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    root = tmp_path_factory.mktemp("median")
    sweep = root / "sweep"
    proc = run_train([*MEDIAN_SWEEP, f"hydra.sweep.dir={sweep}"], cwd=root, check=False)
    return sweep, proc


def test_median_stop_ends_the_jobs_that_do_not_learn_and_the_sweep_exits_0(median_sweep):
    sweep, proc = median_sweep
    check_median_sweep(sweep, proc)
    # The learning jobs really were ahead at the step of each stop.
    for name in STILL:
        step = status(sweep / name)["global_step"]
        own = dict(evals(sweep / name))[step]
        assert all(dict(evals(sweep / n))[step] > own for n in LEARNS)


def test_rlexp_report_lists_the_jobs_stopped_early_and_the_budget_saved(median_sweep):
    sweep, _ = median_sweep
    check_report(sweep)


def test_median_stop_with_the_joblib_launcher(tmp_path):
    """``hydra/launcher=local``: two worker processes; the lr=0 jobs start as the learning ones end."""
    sweep = tmp_path / "sweep"
    proc = run_train(
        [*MEDIAN_SWEEP, "hydra/launcher=local", f"hydra.sweep.dir={sweep}"],
        cwd=tmp_path,
        check=False,
    )
    check_median_sweep(sweep, proc)
