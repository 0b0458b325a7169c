"""SAC learns: Pendulum-v1 with rl-zoo's preset (+experiment=sac: 20k steps, lr 1e-3) reaches a
deterministic evaluation return above -400 (random play: about -1,200; rl-zoo's SAC: about -150)."""

from __future__ import annotations

import json

import pytest

from conftest import run_train


@pytest.mark.slow
def test_sac_learns_pendulum_in_20k_steps(tmp_path):
    run = tmp_path / "run"
    run_train(["env=pendulum", "+experiment=sac", "trainer.eval_every=5000",
               "trainer.eval_episodes=5", "logger=none", f"hydra.run.dir={run}", "seed=0"],
              cwd=tmp_path, timeout=3600)  # fmt: skip
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    evals = [r["eval/episode_return"] for r in rows if "eval/episode_return" in r]
    assert len(evals) >= 4 and evals[-1] > -400, evals
