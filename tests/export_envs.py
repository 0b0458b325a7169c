"""Gymnasium envs for the export tests of grouped and image policies (``env.name=export_envs:<Id>``).

- ``Privileged-v0``: a Dict of what a robot measures (``joints`` Box [3], ``phase`` Discrete(3,
  start=1)) and ``privileged`` simulator state (Box [2]) that only a critic should read; Box
  actions [2] in [-1, 1]. With ``PRIVILEGED = False`` (a deployment without the simulator's state)
  the observation and its space have no ``privileged`` key.
- ``Pixels-v0``: a Dict of a uint8 HWC camera [36, 36, 3], a uint8 CHW ``depth`` [1, 36, 36]
  image and a float32 ``speed`` [2]; Discrete(3) actions (start=-1).

Every value comes from the env's own seeded RNG, so episodes differ and repeat with the seed.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

#: Whether ``Privileged-v0`` gives its privileged state (a test switches it off for deployment).
PRIVILEGED = True


class Privileged(gym.Env):
    """Steer ``joints[:2]`` towards zero; the privileged state is the next step's noise."""

    def __init__(self, length: int = 12) -> None:
        self.length = length
        self.privileged = PRIVILEGED
        obs = {
            "joints": spaces.Box(-5, 5, (3,), np.float32),
            "phase": spaces.Discrete(3, start=1),
        }
        if self.privileged:
            obs["privileged"] = spaces.Box(-1, 1, (2,), np.float32)
        self.observation_space = spaces.Dict(obs)
        self.action_space = spaces.Box(-1, 1, (2,), np.float32)
        self.t = 0

    def _obs(self):
        out = {"joints": self.joints.astype(np.float32), "phase": int(self.t % 3) + 1}
        if self.privileged:
            out["privileged"] = self.noise.astype(np.float32)
        return out

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        self.joints = self.np_random.uniform(-2, 2, 3)
        self.noise = self.np_random.uniform(-1, 1, 2)
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        self.joints[:2] = np.clip(
            self.joints[:2] + 0.5 * np.asarray(action) + 0.1 * self.noise, -5, 5
        )
        self.joints[2] = self.np_random.uniform(-1, 1)
        self.noise = self.np_random.uniform(-1, 1, 2)
        reward = -float(np.abs(self.joints[:2]).sum())
        return self._obs(), reward, False, self.t >= self.length, {}


class Pixels(gym.Env):
    """Random frames; the reward favours the action whose index matches the camera's mean
    brightness tercile."""

    def __init__(self, length: int = 8) -> None:
        self.length = length
        self.observation_space = spaces.Dict(
            {
                "camera": spaces.Box(0, 255, (36, 36, 3), np.uint8),
                "depth": spaces.Box(0, 255, (1, 36, 36), np.uint8),
                "speed": spaces.Box(-3, 3, (2,), np.float32),
            }
        )
        self.action_space = spaces.Discrete(3, start=-1)
        self.t = 0

    def _obs(self):
        rng = self.np_random
        self.level = int(rng.integers(0, 3))
        camera = rng.integers(0, 85, (36, 36, 3)) + 85 * self.level
        return {
            "camera": camera.astype(np.uint8),
            "depth": rng.integers(0, 256, (1, 36, 36)).astype(np.uint8),
            "speed": rng.uniform(-3, 3, 2).astype(np.float32),
        }

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        reward = float(int(action) + 1 == self.level)
        return self._obs(), reward, False, self.t >= self.length, {}


gym.register("Privileged-v0", entry_point=Privileged)
gym.register("Pixels-v0", entry_point=Pixels)
