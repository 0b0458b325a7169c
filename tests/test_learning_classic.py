"""Learning tests on Gymnasium's classic-control and Box2D tasks (issue #28): each preset of
conf/experiment/ (hyperparameters from rl-baselines3-zoo) reaches its task's threshold in
deterministic evaluation, one seed each. Marked slow (minutes); run with `make test-slow`.
Three seeds each, with the time to threshold: benchmarks/classic_control.py (docs/results.md,
"Classic control")."""

from __future__ import annotations

import json

import pytest

from conftest import only_run_dir, run_train

# preset, threshold on the mean eval return, seed, timeout (s: ~5x the run's time on 2 cores)
CASES = [
    pytest.param("cartpole_ppo", 475.0, 0, 600, id="CartPole-v1"),
    pytest.param("acrobot_ppo", -100.0, 0, 900, id="Acrobot-v1"),
    pytest.param("pendulum_ppo", -250.0, 0, 900, id="Pendulum-v1"),
    pytest.param("lunar_lander_ppo", 200.0, 0, 2400, id="LunarLander-v3"),
]


def _eval_returns(run_dir) -> list[tuple[int, float]]:
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [(r["step"], r["eval/episode_return"]) for r in rows if "eval/episode_return" in r]


@pytest.mark.slow
@pytest.mark.parametrize(("preset", "threshold", "seed", "timeout"), CASES)
def test_preset_reaches_threshold(tmp_path, preset, threshold, seed, timeout):
    if preset.startswith("lunar_lander"):
        pytest.importorskip("Box2D", reason='LunarLander needs Box2D: pip install "rlexp[box2d]"')
    # subprocess.run (in run_train) kills the training when the timeout expires
    run_train(
        [f"+experiment={preset}", f"seed={seed}", "trainer.progress=false"],
        cwd=tmp_path,
        timeout=timeout,
    )
    evals = _eval_returns(only_run_dir(tmp_path))
    assert evals and max(r for _, r in evals) >= threshold, f"eval returns by step: {evals}"
