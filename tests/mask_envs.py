"""Gymnasium envs with action masks for the masking tests (issue #48), registered on import:
``env.name=mask_envs:<Id>``.

- ``MaskedMulti-v0``: ``MultiDiscrete([3, 4])`` actions; each step a fresh mask (bool [7]: 3 then 4
  entries) with at least one valid value per component, component 1 often a single one; the mask
  in a ``Dict`` observation key (``mask_in=observation``, key ``mask_key``) or ``info``
  (``mask_in=info``); ``width`` makes it the wrong width. An invalid action ends the episode
  (reward -1); the env counts them (``invalid``) so a test can tell. ``empty_after=N``: from
  its N-th step on, a mask with no valid value.
- ``MaskedBits-v0``: ``MultiBinary(3)`` actions, mask bool [6] in ``info`` (pairs: value 0, 1).
- ``MaskedBox-v0``: ``Box`` actions and an ``info["action_mask"]`` (refused with masking on).
- ``make_masked_vecenv``: an rsl_rl-style VecEnv with the mask in its extras (env.backend=vecenv).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces


class MaskedMulti(gym.Env):
    def __init__(
        self,
        mask_in: str = "observation",
        mask_key: str = "action_mask",
        width: int = 7,
        empty_after: int = 0,
    ):
        self.mask_in, self.mask_key, self.width = mask_in, mask_key, width
        self.empty_after, self.steps = empty_after, 0  # empty_after > 0: then a mask of zeros
        pos = spaces.Box(-1.0, 1.0, (2,), np.float32)
        if mask_in == "observation":
            self.observation_space = spaces.Dict({"pos": pos, mask_key: spaces.MultiBinary(width)})
        else:
            self.observation_space = pos
        self.action_space = spaces.MultiDiscrete([3, 4])
        self.invalid = 0
        self._t = 0

    def _draw(self):
        rng = self.np_random
        a = rng.random(3) < 0.5
        a[rng.integers(3)] = True
        b = np.zeros(4, bool)
        b[rng.integers(4)] = True  # one valid value, sometimes more
        if rng.random() < 0.5:
            b |= rng.random(4) < 0.5
        self._mask = np.concatenate([a, b])
        mask = np.resize(self._mask.astype(np.int8), self.width)
        if self.empty_after and self.steps >= self.empty_after:
            mask[:] = 0
        self._pos = rng.uniform(-1, 1, 2).astype(np.float32)
        if self.mask_in == "observation":
            return {"pos": self._pos, self.mask_key: mask}, {}
        return self._pos, {self.mask_key: mask}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._t = 0
        return self._draw()

    def step(self, action):
        a, b = int(action[0]), int(action[1])
        ok = bool(self._mask[a] and self._mask[3 + b])
        self.invalid += not ok
        self._t += 1
        self.steps += 1
        obs, info = self._draw()
        return obs, 1.0 if ok else -1.0, not ok, self._t >= 10, info


class MaskedBits(gym.Env):
    def __init__(self):
        self.observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.action_space = spaces.MultiBinary(3)

    def _draw(self):
        mask = np.ones(6, np.int8)
        mask[2 * int(self.np_random.integers(3)) + int(self.np_random.integers(2))] = 0
        self._mask = mask
        return self.np_random.uniform(-1, 1, 2).astype(np.float32), {"action_mask": mask}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self._draw()

    def step(self, action):
        bits = np.asarray(action).reshape(-1)
        ok = all(self._mask[2 * i + int(v)] for i, v in enumerate(bits))
        obs, info = self._draw()
        return obs, 1.0 if ok else -1.0, not ok, False, info


class MaskedBox(gym.Env):
    def __init__(self):
        self.observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, np.float32), {"action_mask": np.ones(2, np.int8)}

    def step(self, action):
        return np.zeros(2, np.float32), 0.0, False, False, {"action_mask": np.ones(2, np.int8)}


for _name, _cls in (
    ("MaskedMulti-v0", MaskedMulti),
    ("MaskedBits-v0", MaskedBits),
    ("MaskedBox-v0", MaskedBox),
):
    if _name not in gym.registry:
        gym.register(_name, entry_point=f"{__name__}:{_cls.__name__}", max_episode_steps=50)


class MaskedVecEnv:
    """rsl_rl's VecEnv contract with ``MultiDiscrete([3, 4])`` actions and the action mask in
    ``extras["action_mask"]`` of ``get_observations()`` and ``step()`` (``mask_key``; ``width``
    wrong on purpose); invalid actions end the episode and are counted (``invalid``).
    ``env.name=mask_envs:make_masked_vecenv``."""

    def __init__(self, num_envs: int = 4, seed: int = 0, width: int = 7):
        self.num_envs, self.num_actions, self.device = num_envs, 2, "cpu"
        self.single_action_space = spaces.MultiDiscrete([3, 4])
        self.gen = np.random.default_rng(seed)
        self.width, self.invalid, self.t = width, 0, np.zeros(num_envs, int)
        self._draw()

    def _draw(self):
        n = self.num_envs
        a = self.gen.random((n, 3)) < 0.5
        a[np.arange(n), self.gen.integers(0, 3, n)] = True
        b = np.zeros((n, 4), bool)
        b[np.arange(n), self.gen.integers(0, 4, n)] = True
        self.mask = np.concatenate([a, b], 1)
        self.obs = torch.as_tensor(self.gen.uniform(-1, 1, (n, 3)), dtype=torch.float32)

    def _extras(self):
        mask = torch.as_tensor(np.resize(self.mask, (self.num_envs, self.width)).astype(np.int8))
        return {"action_mask": mask}

    def get_observations(self):
        return self.obs, self._extras()

    def step(self, actions):
        a = actions.numpy()
        rows = np.arange(self.num_envs)
        ok = self.mask[rows, a[:, 0]] & self.mask[rows, 3 + a[:, 1]]
        self.invalid += int((~ok).sum())
        self.t += 1
        time_out = self.t >= 8
        dones = ~ok | time_out
        self.t[dones] = 0
        self._draw()
        extras = {**self._extras(), "time_outs": torch.as_tensor(time_out & ok)}
        reward = torch.as_tensor(np.where(ok, 1.0, -1.0), dtype=torch.float32)
        return self.obs, reward, torch.as_tensor(dones), extras


def make_masked_vecenv(num_envs: int = 4, seed: int = 0, width: int = 7) -> MaskedVecEnv:
    return MaskedVecEnv(num_envs, seed, width)
