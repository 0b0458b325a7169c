"""SAC / TD3 resume: train -> SIGKILL after a checkpoint -> resume ends bit-identical to the
uninterrupted run (actor, twin Q networks, targets, alpha, optimisers, replay buffer, RNGs, env
state), with episodes both terminated (the pole falls) and truncated (an 8-step time limit)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from test_resume import _kill_after_checkpoint, _same

from conftest import run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint

FRAMES = 300  # per half, summed over 2 envs


def _args(algo: str, run_dir: Path) -> list[str]:
    return [
        f"algorithm={algo}",
        "env=inverted_pendulum",
        "env.max_episode_steps=8",
        "env.num_envs=2",
        f"trainer.total_frames={2 * FRAMES}",
        f"trainer.save_every={FRAMES}",
        "trainer.eval_every=0",
        "algorithm.learning_starts=100",
        "algorithm.batch_size=32",
        "algorithm.updates_per_step=0.5",
        "policy.actor.hidden_sizes=[32,32]",
        "policy.critic.hidden_sizes=[32,32]",
        "logger=none",
        f"hydra.run.dir={run_dir}",
        "seed=3",
    ]


@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_sigkill_and_resume_is_bit_identical_with_the_replay_buffer(tmp_path, algo):
    whole, broken = tmp_path / "whole", tmp_path / "broken"
    run_train(_args(algo, whole), cwd=tmp_path, timeout=600)
    _kill_after_checkpoint(_args(algo, broken), tmp_path, broken / "checkpoints", FRAMES)
    proc = run_train(_args(algo, broken), cwd=tmp_path, timeout=600)
    assert "[resume] continuing from" in proc.stdout + proc.stderr
    a = load_checkpoint(latest_checkpoint(whole / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(broken / "checkpoints"))
    assert a["global_step"] == b["global_step"] == 2 * FRAMES
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after resume"
    sa, sb = a["algorithm"], b["algorithm"]
    assert sa["gradient_steps"] == sb["gradient_steps"] == (2 * FRAMES - 100) // 2 + 1
    for key, value in sa["loss"].items():  # twin Q, targets, log_alpha
        assert torch.equal(value, sb["loss"][key]), f"loss.{key} differs after resume"
    assert _same(sa["optimizers"], sb["optimizers"]), "optimiser state differs after resume"
    ra, rb = sa["replay"], sb["replay"]
    assert ra["written"] == rb["written"] == 2 * FRAMES
    assert _same(ra.get("generator"), rb.get("generator")), "replay generator differs"
    assert _same(a["rng"], b["rng"])
