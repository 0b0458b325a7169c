"""algorithm.overlap: the next rollout is collected in a child process while the update runs.

What must hold: each rollout after the first is collected by the policy one update behind (the
behaviour policy whose log-probabilities the loss's ratio uses), the synchronous default is not; the
child ends with the run, and on its own when the training process is killed; settings it cannot
run with are refused before anything is written. Exact resume with a rollout in flight:
tests/test_resume.py."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import psutil
import pytest
import torch

from conftest import REPO, Children, compose
from rlexp.config.validate import ConfigError, to_root_config
from rlexp.training.overlap import OverlapCollector

SMALL = [
    "env=hopper",
    "trainer.frames_per_batch=256",
    "trainer.total_frames=768",
    "trainer.eval_every=0",
    "trainer.save_every=0",
    "algorithm.num_epochs=3",
    "algorithm.mini_batch_size=64",
    "algorithm.lr=3e-3",  # large steps: the policies before and after an update differ clearly
    "algorithm.compile=false",
    "logger=none",
    "trainer.progress=false",
    "seed=11",
]


def _run_recording(tmp_path: Path, overlap: bool) -> tuple[list[dict], list, int | None]:
    """Train SMALL; per update, the policy's state as the update starts and the rollout it learns
    from; the collection child's PID (None: synchronous)."""
    from rlexp.run.metrics import MetricLogger
    from rlexp.training.build import build

    config = to_root_config(compose([*SMALL, f"algorithm.overlap={str(overlap).lower()}"]))
    torch.manual_seed(0)
    objects = build(config, tmp_path, "cpu", config.trainer.total_frames)
    trainer = objects.trainer(MetricLogger([]), {}, {})
    states, batches = [], []
    update = trainer.algorithm.update

    def recording_update(batch):
        states.append({k: v.clone() for k, v in trainer.policy.state_dict().items()})
        batches.append(batch.clone())
        return update(batch)

    trainer.algorithm.update = recording_update
    try:
        trainer.train(config.trainer.total_frames)
        assert isinstance(trainer.collector, OverlapCollector) == overlap
    finally:
        trainer.close()
    return states, batches, getattr(trainer.collector, "pid", -1)  # None: shut down; -1: none


def _loc(policy, state: dict, obs: torch.Tensor) -> torch.Tensor:
    policy.load_state_dict(state)
    with torch.no_grad():
        return policy.actor_net(obs)[0]


@pytest.mark.parametrize("overlap", [True, False], ids=["overlap", "synchronous"])
def test_each_rollout_is_collected_by_the_policy_one_update_behind(tmp_path, overlap):
    states, batches, _ = _run_recording(tmp_path, overlap)
    assert len(batches) == 3
    from rlexp.training.build import build

    config = to_root_config(compose(SMALL))
    policy = build(config, tmp_path / "probe", "cpu", 256).policy
    for k in (1, 2):
        obs, stored = batches[k]["observation"], batches[k]["loc"]
        behind = _loc(policy, states[k - 1], obs)  # before the previous update
        current = _loc(policy, states[k], obs)  # before this update (after the previous one)
        assert not torch.allclose(behind, current, atol=1e-3), "the updates changed nothing"
        collected_by = behind if overlap else current
        other = current if overlap else behind
        torch.testing.assert_close(stored, collected_by, atol=2e-5, rtol=1e-4)
        assert not torch.allclose(stored, other, atol=1e-3)
    # The first rollout: the initial policy either way.
    torch.testing.assert_close(
        batches[0]["loc"], _loc(policy, states[0], batches[0]["observation"]), atol=2e-5, rtol=1e-4
    )


def test_the_collection_child_ends_with_the_run(tmp_path):
    _, _, pid = _run_recording(tmp_path, overlap=True)
    assert pid is None, "close() did not shut the collection child down"


def _child_pids(pid: int) -> list[int]:
    try:
        return [c.pid for c in psutil.Process(pid).children()]
    except psutil.NoSuchProcess:
        return []


def _gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _kill_the_training_process_and_check_the_child_ends(
    tmp_path: Path, args: list[str], ready: str, env_extra: dict[str, str] | None = None
) -> None:
    """Start ``train.py args``; once its train.log shows ``ready`` (and its collection child
    exists), SIGKILL the training process alone (no chance to clean up): the child must end by
    itself within seconds."""
    log = tmp_path / "run" / "train.log"
    with Children() as children:
        proc = children.train([*args, f"hydra.run.dir={tmp_path / 'run'}"], tmp_path,
                              tmp_path / "run.txt", env_extra=env_extra)  # fmt: skip
        deadline, forked = time.time() + 120, []
        while time.time() < deadline and proc.poll() is None and not forked:
            if log.exists() and ready in log.read_text():
                forked = _child_pids(proc.pid)
            time.sleep(0.05)
        assert forked, f"no collection child: {(tmp_path / 'run.txt').read_text()[-2000:]}"
        time.sleep(1.0)  # a rollout in flight (or stuck in its step)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        deadline = time.time() + 20
        while time.time() < deadline and not all(_gone(p) for p in forked):
            time.sleep(0.05)
        assert all(_gone(p) for p in forked), "the collection child outlived the training process"


def test_the_collection_child_ends_when_the_training_process_is_killed(tmp_path):
    """The child waiting on its pipe, or finishing a rollout: the pipe's end stops it."""
    args = [
        *SMALL[1:],
        "env=half_cheetah",
        "trainer.total_frames=10000000",
        "algorithm.overlap=true",
    ]
    _kill_the_training_process_and_check_the_child_ends(tmp_path, args, "[train] step=2048")


def test_a_collection_child_stuck_in_an_env_step_ends_with_the_training_process(tmp_path):
    """stuck_envs:StuckAfter-v0 hangs forever in step 301, inside the child's second rollout; the
    child never reads its pipe again, and still ends when the training process is killed."""
    args = ["env=hopper", "env.name=stuck_envs:StuckAfter-v0", "+env.kwargs.after=300",
            "env.num_envs=1", "trainer.frames_per_batch=256", "trainer.eval_every=0",
            "trainer.total_frames=100000", "algorithm.num_epochs=1", "trainer.progress=false",
            "algorithm.overlap=true", "logger=none"]  # fmt: skip
    extra = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{REPO / 'tests'}", "MUJOCO_GL": "egl"}
    _kill_the_training_process_and_check_the_child_ends(tmp_path, args, "[overlap]", extra)


def test_settings_overlap_cannot_run_with_are_refused_naming_the_key(tmp_path):
    with pytest.raises(ConfigError, match=r"algorithm.overlap=true .*env.backend='envpool'"):
        to_root_config(compose(["env=hopper", "env.backend=envpool", "algorithm.overlap=true"]))
    with pytest.raises(ConfigError, match=r"events.train \(observation_noise, action_noise\)"):
        to_root_config(compose(["env=push_cube", "events=noise", "algorithm.overlap=true"]))
    from rlexp.training.build import build

    config = to_root_config(compose(["env=hopper", "algorithm.overlap=true"]))
    with pytest.raises(ConfigError, match="device 'cuda'.*trainer.device=cpu"):
        build(config, tmp_path, "cuda", 1000)
    with pytest.raises(Exception, match="overlap"):  # a PPO option: GRPO has no such key
        compose(["algorithm=grpo", "policy=actor_only", "algorithm.overlap=true"])


def test_each_rollout_draws_new_action_noise(tmp_path):
    """The child's generator is seeded anew for every rollout (from this process's generator): two
    rollouts' noise, read back as (action - loc) / scale, is standard normal and uncorrelated, not
    one rollout's noise again. A child seeded alike every rollout is deterministic and resumes
    exactly (the resume tests pass), yet acts with the same noise each time."""
    _, batches, _ = _run_recording(tmp_path, overlap=True)
    noise = [((b["action"] - b["loc"]) / b["scale"]).reshape(-1) for b in batches]
    assert len(noise) == 3 and noise[0].numel() == 256 * 3  # 256 steps x 3 action dims
    for k, x in enumerate(noise):  # N(0, 1): 768 values, bounds at > 5 standard errors
        assert abs(float(x.mean())) < 0.2 and 0.85 < float(x.std()) < 1.15, (k, x.mean(), x.std())
    for k in (0, 1):
        corr = float(torch.corrcoef(torch.stack([noise[k], noise[k + 1]]))[0, 1])
        assert abs(corr) < 0.2, f"rollouts {k} and {k + 1}: noise correlation {corr:.3f}"
