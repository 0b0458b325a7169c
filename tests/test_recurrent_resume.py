"""A recurrent policy's run killed mid-episode (SIGKILL after a checkpoint) and resumed ends
bit-identical to the uninterrupted run: the checkpoint holds the hidden state the collector
carries between steps and which envs start an episode next."""

from __future__ import annotations

import torch

from rlexp.checkpoints.files import load_checkpoint, step_checkpoints
from test_resume import _assert_resume_is_exact

LSTM = [
    "policy.memory.type=lstm",
    "policy.memory.hidden_size=16",
    "policy.memory.num_layers=2",
    "algorithm.sequence_length=8",
    "env.num_envs=4",
]


def _assert_mid_episode(run_dir, step: int, num_envs: int) -> None:
    """The interrupted run's checkpoint at ``step`` holds a carried state, mid-episode."""
    ckpt = [p for p in step_checkpoints(run_dir / "checkpoints") if p.stem.endswith(f"{step:09d}")]
    carry = load_checkpoint(ckpt[0])["recurrent_carry"]
    assert sorted(carry["state"]) == ["actor_c", "actor_h", "critic_c", "critic_h"]
    assert carry["state"]["actor_h"].shape == torch.Size([num_envs, 2, 16])
    running = ~carry["is_init"].reshape(-1)
    assert running.any(), "every env was at an episode's start: the test would be vacuous"
    assert carry["state"]["actor_h"][running].abs().sum(-1).gt(0).all()


def test_sigkill_mid_episode_and_resume_is_bit_identical_lstm_native_cart_pole(tmp_path):
    """rlexp's native cart-pole (its state restores exactly; Gymnasium's CartPole-v1 has no
    get_state, so a resume restarts its episodes)."""
    _assert_resume_is_exact(tmp_path, "cart_pole", frames=512, batch=256, extra=LSTM)
    _assert_mid_episode(tmp_path / "broken", 512, 4)


def test_sigkill_mid_episode_and_resume_is_bit_identical_gru_gymnasium(tmp_path):
    gru = [*LSTM[1:], "policy.memory.type=gru", "policy.memory.shared=true"]
    _assert_resume_is_exact(tmp_path, "inverted_pendulum", frames=512, batch=256, extra=gru)
