"""Learning tests: the agent really improves. Marked slow (minutes); run with `make test-slow`."""

from __future__ import annotations

import json

import pytest

from conftest import only_run_dir, run_train


@pytest.mark.slow
def test_inverted_pendulum_reaches_800_within_200k_steps(tmp_path):
    run_train(
        [
            "env=inverted_pendulum",
            "trainer.total_frames=200000",
            "trainer.eval_every=20000",
            "trainer.eval_episodes=10",
            "trainer.save_every=0",
            "seed=1",
        ],
        cwd=tmp_path,
        timeout=1800,
    )
    rows = [
        json.loads(x) for x in (only_run_dir(tmp_path) / "metrics.jsonl").read_text().splitlines()
    ]
    evals = [(r["step"], r["eval/episode_return"]) for r in rows if "eval/episode_return" in r]
    assert evals and max(r for _, r in evals) >= 800, f"eval returns by step: {evals}"


def _evals(tmp_path) -> list[tuple[int, float, float]]:
    rows = [
        json.loads(x) for x in (only_run_dir(tmp_path) / "metrics.jsonl").read_text().splitlines()
    ]
    return [
        (r["step"], r["eval/episode_return"], r["eval/success_rate"])
        for r in rows
        if "eval/episode_return" in r
    ]


@pytest.mark.slow
def test_cart_pole_is_solved_within_2m_steps(tmp_path):
    """Max return is 500 (upright reward 1 per step, 500 steps): solved = mean eval >= 475 (95%).
    The run must reach it within the budget, and what it delivers for that, ``best.pt``, must still
    score >= 475 on 50 fresh episodes (another seed) through ``rlexp eval``'s code path. Measured here
    (seed 0): 499.8 at 1.57M and 1.77M steps, 469 at the last eval (1.97M); ~60 s of wall time."""
    run_train(
        [
            "env=cart_pole",
            "trainer.total_frames=2000000",
            "trainer.frames_per_batch=16384",
            "algorithm.mini_batch_size=4096",
            "algorithm.num_epochs=5",
            "trainer.eval_every=196608",
            "trainer.eval_episodes=16",
            "trainer.save_every=0",
        ],
        cwd=tmp_path,
        timeout=1800,
    )
    evals = _evals(tmp_path)
    assert max(r for _, r, _ in evals) >= 475, f"eval (step, return, success) by step: {evals}"
    from rlexp.cli import evaluate

    best = evaluate(str(next(tmp_path.rglob("checkpoints/best.pt"))), 50, None, seed=999)
    assert best["episodes"] == 50 and best["mean_return"] >= 475, f"best.pt: {best}; evals: {evals}"


@pytest.mark.slow
def test_push_cube_reaches_success_0_8_within_6m_steps(tmp_path):
    """The +experiment=push_cube_ppo preset (gamma 0.9; see its comment). Measured here, seed 0:
    eval success 0.66-0.69 from 2.9M steps, 0.88 at 4.46M, 0.91 at 4.72M, 0.72 at 5.77M; 6M steps
    took 16.8 min (about 6,000 env steps/s with 64 envs, the loss compiled by compile=auto)."""
    run_train(["+experiment=push_cube_ppo", "seed=0"], cwd=tmp_path, timeout=3600)
    evals = _evals(tmp_path)
    assert max(s for _, _, s in evals) >= 0.8, f"eval (step, return, success): {evals}"


@pytest.mark.slow
def test_grpo_cart_pole_is_solved_within_2_5m_steps(tmp_path):
    """GRPO with the users' CartPole settings (+experiment=cart_pole_grpo: 64 envs x 1024 steps,
    actor-only 256x256 ReLU, lr 1e-4, minibatch 8192, entropy 0.01, no KL, groups of 4) reaches the
    solved level (eval >= 475 of 500). Measured here (docs/grpo.md), 2M-step runs: seed 0 first
    reached it at 1.77M steps (499.95), seed 1 at 1.97M (499.89); seed 2 was at 394 at 1.97M. 2.5M
    steps (39 iterations) is seed 0's 1.77M with ~40% margin; 3-6 min on the 2-core VM (load-dependent)."""
    run_train(
        [
            "+experiment=cart_pole_grpo",
            "seed=0",
            "trainer.total_frames=2500000",
            "trainer.save_every=0",
        ],
        cwd=tmp_path,
        timeout=3600,
    )
    rows = [
        json.loads(x) for x in (only_run_dir(tmp_path) / "metrics.jsonl").read_text().splitlines()
    ]
    evals = [(r["step"], r["eval/episode_return"]) for r in rows if "eval/episode_return" in r]
    masks = [r["grpo/mask_fraction"] for r in rows if "grpo/mask_fraction" in r]
    assert masks and all(0.0 < m <= 500 / 1024 for m in masks), f"mask fractions: {masks}"
    assert evals and max(r for _, r in evals) >= 475, f"eval returns by step: {evals}"
