"""``trainer.precision=bf16`` learns: the float32 learning checks, with bf16. CartPole-v1 with the
rl-zoo PPO preset reaches 475 in deterministic evaluation (tests/test_learning_classic.py's
threshold), Pendulum-v1 with rl-zoo's SAC preset above -400 (tests/test_sac_learning.py's). Slow
(minutes): ``make test-slow``."""

from __future__ import annotations

import json

import pytest

from conftest import only_run_dir, run_train


def _evals(run_dir) -> list[float]:
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [r["eval/episode_return"] for r in rows if "eval/episode_return" in r]


@pytest.mark.slow
def test_bf16_ppo_learns_cartpole(tmp_path):
    run_train(
        ["+experiment=cartpole_ppo", "seed=0", "trainer.precision=bf16", "trainer.progress=false"],
        cwd=tmp_path,
        timeout=900,
    )
    run = only_run_dir(tmp_path)
    assert "precision: bf16" in (run / "config.yaml").read_text()
    evals = _evals(run)
    assert evals and max(evals) >= 475.0, evals


@pytest.mark.slow
def test_bf16_sac_learns_pendulum(tmp_path):
    run = tmp_path / "run"
    run_train(["env=pendulum", "+experiment=sac", "trainer.precision=bf16",
               "trainer.eval_every=5000", "trainer.eval_episodes=5", "logger=none",
               f"hydra.run.dir={run}", "seed=0"], cwd=tmp_path, timeout=3600)  # fmt: skip
    evals = _evals(run)
    assert len(evals) >= 4 and evals[-1] > -400, evals
