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
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
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
