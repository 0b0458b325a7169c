"""Resume: an interrupted run (SIGKILL after a checkpoint) continued from its checkpoint ends with
bit-identical parameters to an uninterrupted run; corrupt checkpoints are skipped."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import Children, needs_compiler, run_train
from rlexp.checkpoints.files import (
    latest_checkpoint,
    latest_good_checkpoint,
    load_checkpoint,
    step_checkpoints,
)


def _cmd(
    env: str, run_dir: Path, frames: int, batch: int, extra: list[str], eval_every: int = 0
) -> list[str]:
    return [
        f"env={env}",
        f"trainer.total_frames={2 * frames}",
        f"trainer.frames_per_batch={batch}",
        f"trainer.save_every={frames}",
        f"trainer.eval_every={eval_every}",
        "algorithm.num_epochs=2",
        f"hydra.run.dir={run_dir}",
        "seed=5",
        *extra,
    ]


def _kill_after_checkpoint(
    args: list[str],
    cwd: Path,
    ckpt_dir: Path,
    step: int,
    env_extra: dict[str, str] | None = None,
    sig: int = signal.SIGKILL,
) -> int:
    """``train.py args``, sent ``sig`` once the checkpoint of ``step`` exists (SIGKILL: to the
    process; another signal: to its process group, as a terminal's Ctrl-C is); its process group
    is killed when this returns or fails (``Children``); ``env_extra``: more environment variables.
    The run's PID (its session id: it leads a session of its own)."""
    with Children() as children:
        proc = children.train(args, cwd, cwd / "killed-run.txt", env_extra=env_extra)
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None:
            if any(p.name.endswith(f"_step_{step:09d}.pt") for p in ckpt_dir.glob("*.pt")):
                if sig == signal.SIGKILL:
                    proc.send_signal(sig)
                else:
                    os.killpg(proc.pid, sig)
                break
            time.sleep(0.02)
        proc.wait(timeout=60)
    expected = -sig if sig == signal.SIGKILL else 128 + sig  # rlexp stops with 128 + signal
    assert proc.returncode == expected, (
        f"the run was not stopped mid-way: {(cwd / 'killed-run.txt').read_text()}"
    )
    steps = [int(p.stem.rsplit("_", 1)[1]) for p in step_checkpoints(ckpt_dir)]
    assert max(steps) < 2 * step, "the run finished before it was killed"
    return proc.pid


def _same(a, b) -> bool:
    """Equality through dicts, lists, tensors and arrays (event and RNG states hold all of them)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and torch.equal(a, b)
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and np.array_equal(a, b)
    return a == b


def _assert_resume_is_exact(
    tmp_path: Path,
    env: str,
    frames: int,
    batch: int,
    extra: list[str],
    eval_every: int = 0,
    sig: int = signal.SIGKILL,
) -> None:
    whole, broken = tmp_path / "whole", tmp_path / "broken"
    run_train(_cmd(env, whole, frames, batch, extra, eval_every), cwd=tmp_path, timeout=600)
    _kill_after_checkpoint(
        _cmd(env, broken, frames, batch, extra, eval_every),
        tmp_path,
        broken / "checkpoints",
        frames,
        sig=sig,
    )
    proc = run_train(_cmd(env, broken, frames, batch, extra, eval_every), cwd=tmp_path, timeout=600)
    assert "[resume] continuing from" in proc.stdout + proc.stderr
    a = load_checkpoint(latest_checkpoint(whole / "checkpoints"))
    b = load_checkpoint(latest_checkpoint(broken / "checkpoints"))
    assert a["global_step"] == b["global_step"] == 2 * frames
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), f"policy.{key} differs after resume"
    for i, state in a["algorithm"]["optimizer"]["state"].items():
        for k, v in state.items():
            assert torch.equal(v, b["algorithm"]["optimizer"]["state"][i][k]), (
                f"optimizer state {i}.{k} differs"
            )
    assert a["windows"]["returns"] == b["windows"]["returns"]
    assert a["last_eval"] == b["last_eval"] and a["best_metric"] == b["best_metric"]
    assert _same(a["events"], b["events"]), "event state (counters, RNG) differs after resume"
    if eval_every:
        assert a["last_eval"], "no evaluation ran: the comparison would be vacuous"
        best_a, best_b = (load_checkpoint(d / "checkpoints" / "best.pt") for d in (whole, broken))
        assert best_a["global_step"] == best_b["global_step"]
        for key, value in best_a["policy"].items():
            assert torch.equal(value, best_b["policy"][key]), f"best.pt policy.{key} differs"


def test_sigkill_and_resume_is_bit_identical_gymnasium(tmp_path):
    _assert_resume_is_exact(tmp_path, "hopper", frames=1024, batch=256, extra=[])


def test_corrupt_checkpoint_falls_back_to_the_previous_one(tmp_path, caplog):
    run_dir = tmp_path / "run"
    args = ["env=inverted_pendulum", "trainer.total_frames=768", "trainer.frames_per_batch=256",
            "trainer.save_every=256", "trainer.eval_every=0", "algorithm.num_epochs=1",
            f"hydra.run.dir={run_dir}"]  # fmt: skip
    run_train(args, cwd=tmp_path)
    ckpts = step_checkpoints(run_dir / "checkpoints")
    assert len(ckpts) == 3
    ckpts[-1].write_bytes(ckpts[-1].read_bytes()[:1000])  # truncated write: the job died mid-save
    (run_dir / "status.json").write_text('{"state": "running", "global_step": 768}')
    with caplog.at_level("WARNING"):
        good = latest_good_checkpoint(run_dir / "checkpoints")
    assert good is not None and good["global_step"] == 512
    assert "unreadable" in caplog.text and ckpts[-1].name in caplog.text
    with pytest.raises(ValueError, match="unreadable"):
        load_checkpoint(ckpts[-1])
    # The resumed run continues from the good one and replaces the broken file.
    proc = run_train(args, cwd=tmp_path)
    assert "step_000000512.pt" in proc.stdout + proc.stderr
    assert load_checkpoint(ckpts[-1])["global_step"] == 768


def test_sigkill_and_resume_is_bit_identical_push_cube(tmp_path):
    """The acceptance test of the lifecycle issue: PushCube, killed mid-run, resumed, bit-identical."""
    _assert_resume_is_exact(
        tmp_path,
        "push_cube",
        frames=1024,
        batch=256,
        extra=["env.num_envs=8", "env.num_eval_envs=2", "policy=mlp_256"],
    )


#: PushCube with periodic evaluation (its own envs, best.pt) on a short episode limit.
EVAL_EXTRA = ["env.num_envs=4", "env.num_eval_envs=2", "trainer.eval_episodes=2",
              "env.max_episode_steps=50"]  # fmt: skip


def test_sigkill_and_resume_is_bit_identical_with_evaluation_and_an_event(tmp_path):
    """Periodic evaluation and a step event drawing from the event manager's RNG (action noise):
    the continuation still matches the uninterrupted run bit for bit, best.pt included."""
    extra = [*EVAL_EXTRA, "events=noise", "~events.train.observation_noise"]
    _assert_resume_is_exact(tmp_path, "push_cube", 512, 256, extra, eval_every=256)


@pytest.mark.parametrize(
    ("env", "extra", "sig"),
    [
        pytest.param("hopper", [], signal.SIGKILL, id="gymnasium-sigkill"),
        pytest.param("push_cube", EVAL_EXTRA, signal.SIGINT, id="native-ctrl-c"),
    ],
)
def test_resume_with_a_rollout_in_flight_is_bit_identical_with_overlap(tmp_path, env, extra, sig):
    """algorithm.overlap=true: a checkpoint mid-run holds the rollout collected ahead (in the child
    while the update ran) and the envs as it left them; the resumed run learns from it first and
    ends where the uninterrupted one does, bit for bit (evaluation included)."""
    extra = ["algorithm.overlap=true", "trainer.keep_last=0", *extra]
    _assert_resume_is_exact(tmp_path, env, 512, 256, extra, eval_every=256, sig=sig)
    (mid_path,) = [p for p in step_checkpoints(tmp_path / "whole" / "checkpoints")
                   if p.name.endswith("_step_000000512.pt")]  # fmt: skip
    mid = load_checkpoint(mid_path)
    pending = mid["pending_rollout"]
    assert pending is not None, "the mid-run checkpoint holds no rollout collected ahead"
    assert pending["batch_size"][0] * pending["batch_size"][1] == 256
    final = load_checkpoint(latest_checkpoint(tmp_path / "whole" / "checkpoints"))
    assert final["pending_rollout"] is None, "the last rollout collected more than the run asked"


# Found by the test above with other events (were strict xfails): a step event's observation noise
# is part of what the policy acts on next (checkpointed as pending_observation), and a resumed env's
# first reset hands back its episodes, so no reset events fire there.
@pytest.mark.parametrize(
    "events",
    [
        pytest.param(["events=noise", "~events.train.action_noise"], id="observation_noise"),
        pytest.param(["events=domain_randomization"], id="randomize_physics"),
    ],
)
def test_sigkill_and_resume_is_bit_identical_with_events_that_touch_observations_and_resets(
    tmp_path, events
):
    _assert_resume_is_exact(tmp_path, "push_cube", 512, 256, [*EVAL_EXTRA, *events], 256)


@needs_compiler
def test_sigkill_and_resume_is_bit_identical_with_the_compiled_loss(tmp_path):
    """algorithm.compile=true: the resumed process compiles again at a different point of the run
    (compiling draws random numbers, and TorchRL's compiled entropy draws a sample every call); the
    continuation must still be bit-identical."""
    extra = ["env.num_envs=4", "env.num_eval_envs=0", "algorithm.compile=true",
             "algorithm.entropy_coeff=0.01", "algorithm.mini_batch_size=64"]  # fmt: skip
    _assert_resume_is_exact(tmp_path, "push_cube", frames=512, batch=256, extra=extra)
    logs = "".join(p.read_text() for p in tmp_path.rglob("train.log"))
    assert logs.count("[ppo] loss compiled in") == 3, "each of the three processes compiles once"


def test_a_run_dir_refuses_a_different_experiment(tmp_path):
    run_dir = tmp_path / "run"
    base = [
        "env=inverted_pendulum",
        "trainer.frames_per_batch=256",
        "trainer.save_every=256",
        "trainer.eval_every=0",
        "algorithm.num_epochs=1",
        f"hydra.run.dir={run_dir}",
    ]
    run_train([*base, "trainer.total_frames=256"], cwd=tmp_path)
    proc = run_train(
        [*base, "trainer.total_frames=512", "algorithm.clip_epsilon=0.3"], cwd=tmp_path, check=False
    )
    assert proc.returncode == 2
    assert (
        "holds a different experiment (differs in algorithm.clip_epsilon)"
        in proc.stdout + proc.stderr
    )
    # Training longer is a continuation, not a different experiment.
    proc = run_train([*base, "trainer.total_frames=512"], cwd=tmp_path)
    assert load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))["global_step"] == 512
