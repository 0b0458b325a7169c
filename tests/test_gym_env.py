"""The Gymnasium adapter: TorchRL specs, float32, clipping, auto-reset with true final observations."""

from __future__ import annotations

import numpy as np
import torch
from torchrl.envs.utils import check_env_specs

from rlexp.envs.gym import GymnasiumEnv


def test_specs_and_float32():
    env = GymnasiumEnv("HalfCheetah-v5", num_envs=2)
    check_env_specs(env)
    td = env.reset()
    assert td["observation"].dtype == torch.float32 and td["observation"].shape == (2, 17)
    env.close()


def test_truncation_keeps_final_observation_and_resets_inside_step():
    env = GymnasiumEnv("InvertedPendulum-v5", num_envs=2, max_episode_steps=5)
    env.set_seed(0)
    td = env.reset()
    for _ in range(5):
        td["action"] = torch.zeros(2, 1)
        out, td = env.step_and_maybe_reset(td)
    nxt = out["next"]
    assert nxt["truncated"].all() and not nxt["terminated"].any() and nxt["done"].all()
    # "next" holds the final observation of the finished episode; the carried td the fresh reset one.
    assert not torch.equal(nxt["observation"], td["observation"])
    assert td["observation"].abs().max() < 0.011  # InvertedPendulum resets near zero (noise 0.01)
    env.close()


def test_actions_are_clipped_to_the_box():
    env = GymnasiumEnv("InvertedPendulum-v5", num_envs=1)
    env.set_seed(0)
    td = env.reset()
    td["action"] = torch.full((1, 1), 100.0)
    env.step(td)
    assert np.allclose(env._envs[0].unwrapped.data.ctrl, 3.0)
    env.close()


def test_same_seed_same_trajectory():
    def rollout(seed):
        env = GymnasiumEnv("Hopper-v5", num_envs=2)
        env.set_seed(seed)
        td = env.reset()
        obs = []
        g = torch.Generator().manual_seed(0)
        for _ in range(50):
            td["action"] = torch.rand(2, 3, generator=g) * 2 - 1
            out, td = env.step_and_maybe_reset(td)
            obs.append(out["next", "observation"])
        env.close()
        return torch.stack(obs)

    assert torch.equal(rollout(3), rollout(3))
    assert not torch.equal(rollout(3), rollout(4))


def test_mujoco_warnings_while_building_go_to_the_log_not_stdout_or_the_working_directory(
    tmp_path, monkeypatch, capfd, caplog
):
    """MuJoCo 4.0 warns that Gymnasium's own XML uses ``settotalmass`` at every model compile
    (stdout, and a MUJOCO_LOG.TXT in the working directory): dropped. Any other MuJoCo warning
    while building goes to the log; MuJoCo's own handler is back afterwards."""
    import logging

    import mujoco

    from rlexp.envs import gym_ids as gym_adapter

    monkeypatch.chdir(tmp_path)
    capfd.readouterr()
    with caplog.at_level(logging.WARNING, logger="rlexp.envs.gym_ids"):
        GymnasiumEnv("Hopper-v5", num_envs=2).reset()
        out, err = capfd.readouterr()
        assert "settotalmass" not in out + err
        assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
        assert not caplog.records
        with gym_adapter.mujoco_build_warnings("Hopper-v5"):
            mujoco.get_mju_user_warning()("something the user should see")
    assert [r.getMessage() for r in caplog.records] == ["[mujoco] something the user should see"]
    assert mujoco.get_mju_user_warning() is None
