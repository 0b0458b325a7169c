"""A user env whose ``step`` never returns after a number of steps (``env.name=stuck_envs:StuckAfter-v0``,
``+env.kwargs.after=N``): a loop stuck in user code, for tests/test_stalls.py."""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class StuckAfter(gym.Env):
    """A 1-D point pushed by a Box action; step number ``after + 1`` of this copy sleeps forever
    (a simulator that hangs, a remote env that never answers)."""

    observation_space = spaces.Box(-5.0, 5.0, (1,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, after: int = 300) -> None:
        self.after = after
        self.steps = 0
        self.x = 0.0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = float(self.np_random.uniform(-1, 1))
        return np.array([self.x], np.float32), {}

    def step(self, action):
        self.steps += 1
        while self.steps > self.after:
            time.sleep(3600)  # a signal interrupts the sleep, runs its handler, and it goes on
        self.x = float(np.clip(self.x + 0.1 * float(np.asarray(action).reshape(-1)[0]), -5, 5))
        return np.array([self.x], np.float32), -abs(self.x), False, False, {}


if "StuckAfter-v0" not in gym.registry:
    gym.register("StuckAfter-v0", entry_point=f"{__name__}:StuckAfter", max_episode_steps=50)
