"""A run's own evaluation, ``rlexp eval`` of its checkpoint and ``rlexp eval`` of its export give the
same numbers, exactly, on envs that keep state across resets (#45): Box2D's BipedalWalker reuses its
physics world (its contact order then depends on earlier episodes) and a user's env may keep
anything. Every eval round (in the training process or in the eval worker) starts from freshly made
env copies, as ``rlexp eval``'s fresh env does; the last of several rounds is the one compared."""

from __future__ import annotations

import os
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from conftest import REPO, run_train
from rlexp.checkpoints.files import latest_checkpoint, load_checkpoint

TESTS = Path(__file__).resolve().parent
PYPATH = {"PYTHONPATH": f"{REPO / 'src'}{os.pathsep}{TESTS}"}

#: 4 eval rounds on the same eval env copies: the last one is what the checkpoint holds.
ROUNDS = [
    "env=hopper",
    "trainer.frames_per_batch=256",
    "trainer.total_frames=1024",
    "trainer.eval_every=256",
    "trainer.save_every=1024",
    "trainer.eval_episodes=3",
    "env.num_eval_envs=2",
    "algorithm.num_epochs=1",
    "trainer.progress=false",
    "seed=5",
]


def _agree(run_dir: Path, tmp_path: Path) -> None:
    """The run's last eval == rlexp eval RUN (its defaults) == rlexp eval of its TorchScript export."""
    from rlexp.deploy.export import export_policy
    from rlexp.deploy.policy_eval import evaluate

    ckpt = load_checkpoint(latest_checkpoint(run_dir / "checkpoints"))
    logged = ckpt["last_eval"]
    assert ckpt["global_step"] == 1024 and logged, ckpt["last_eval"]
    want = (logged["eval/episode_return"], logged["eval/episode_return_std"])
    res = evaluate(str(run_dir), None, None)  # what `rlexp eval RUN` runs
    assert res["episodes"] == 3
    assert (res["mean_return"], res["std_return"]) == want, (res, logged)
    out = export_policy(run_dir, "torchscript", tmp_path / "policy.pt")
    exported = evaluate(str(out.path), None, None)
    assert (exported["mean_return"], exported["std_return"]) == want, (exported, logged)


@pytest.mark.parametrize("backend", ["gymnasium", "gymnasium_async"])
@pytest.mark.parametrize("env_id", ["toy_envs:WornTrack-v0", "BipedalWalker-v3"])
def test_a_reseeded_env_repeats_its_episodes_whatever_its_copies_kept(env_id, backend):
    """The premise (the same seed on a used copy gives another episode), then the contract every
    eval round relies on: after ``set_seed(s)`` the env's episodes are those of an env built now
    with seed ``s``, round after round."""
    import torch
    import toy_envs  # noqa: F401  (registers WornTrack-v0)

    from rlexp.envs.gym import GymnasiumEnv
    from rlexp.envs.gym_async import AsyncGymnasiumEnv

    if env_id.startswith("Bipedal"):
        pytest.importorskip("Box2D")
    gain = torch.linspace(-0.6, 0.9, 24 if env_id.startswith("Bipedal") else 2)

    def episode(env) -> float:
        obs, _ = env.reset(seed=3)
        total = 0.0
        for _ in range(150):
            act = np.tanh(np.full(env.action_space.shape, float(gain[: len(obs)] @ obs)))
            obs, r, term, _, _ = env.step(act.astype(np.float32))
            total += r
            if term:
                break
        return total

    if env_id.startswith("toy_envs"):
        one = gym.make(env_id)
        assert episode(one) != episode(one)  # the same seed, another outcome: the wear

    def round_(env) -> float:
        env.set_seed(9)
        obs = env.reset().get("observation")
        total = 0.0
        for _ in range(150):
            act = torch.tanh(obs @ gain[: obs.shape[-1]]).unsqueeze(-1).expand(-1, env.act_dim)
            nxt = env.step_action(act.contiguous())
            total += float(nxt.get("reward").sum())
            obs = env.autoreset_observation(nxt)
        return total

    cls = GymnasiumEnv if backend == "gymnasium" else AsyncGymnasiumEnv
    env = cls(env_id, 2, 150)
    try:
        rounds = [round_(env) for _ in range(3)]
    finally:
        env.close()
    fresh = GymnasiumEnv(env_id, 2, 150)
    try:
        assert rounds == [round_(fresh)] * 3, rounds
    finally:
        fresh.close()


def test_a_user_env_with_state_across_resets_evaluates_as_its_run_did(tmp_path):
    run_dir = tmp_path / "worn"
    run_train(
        [*ROUNDS, "env.name=toy_envs:WornTrack-v0", f"hydra.run.dir={run_dir}"],
        cwd=tmp_path,
        env_extra=PYPATH,
    )
    _agree(run_dir, tmp_path)


@pytest.mark.parametrize("eval_async", ["false", "true"])
def test_box2d_bipedal_walker_evaluates_as_its_run_did(tmp_path, eval_async):
    """BipedalWalker-v3, 300-step episodes (the walker falls in some): in the training process and in the eval worker."""
    pytest.importorskip("Box2D")
    run_dir = tmp_path / "walker"
    run_train(
        [
            *ROUNDS,
            "env.name=BipedalWalker-v3",
            "env.max_episode_steps=300",
            f"trainer.eval_async={eval_async}",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=tmp_path,
    )
    _agree(run_dir, tmp_path)
