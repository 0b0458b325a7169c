"""Learning tests: the agent really improves. Marked slow (minutes); run with `make test-slow`."""

from __future__ import annotations

import json

import pytest

from conftest import only_run_dir, run_train


@pytest.mark.slow
def test_inverted_pendulum_reaches_800_within_200k_steps(tmp_path):
    run_train(
        ["env=inverted_pendulum", "trainer.total_frames=200000", "trainer.eval_every=20000",
         "trainer.eval_episodes=10", "trainer.save_every=0", "seed=1"],
        cwd=tmp_path, timeout=1800,
    )
    rows = [json.loads(x) for x in (only_run_dir(tmp_path) / "metrics.jsonl").read_text().splitlines()]
    evals = [(r["step"], r["eval/episode_return"]) for r in rows if "eval/episode_return" in r]
    assert evals and max(r for _, r in evals) >= 800, f"eval returns by step: {evals}"
