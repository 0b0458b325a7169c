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
