"""Small Gymnasium envs of the kinds users bring, registered when this module is imported, so that
tests name them as ``env.name=toy_envs:<Id>`` (Gymnasium's ``module:EnvId`` syntax).

- ``DictGoal-v0``: Dict observations (a Box, a nested Dict, a Discrete), MultiDiscrete actions,
  ``get_state`` / ``set_state`` (exact resume), its own RNG draws at every reset and step.
- ``NoStateWalk-v0``: Box observations, Discrete actions (``start=-1``), no state protocol.
- ``BadState-v0``: a ``get_state`` with an object in it (refused at config check).
- ``Throttle-v0``: Box actions in ``[0, 5] x [-3, 1]``, a Dict observation with a Discrete in it.
- ``ImageObs-v0``, ``TextObs-v0``, ``TupleAction-v0``: spaces rlexp refuses.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class DictGoal(gym.Env):
    """Move a point on a 5x5 grid towards a goal: actions (dx, dy) in {-1, 0, 1}^2 as
    MultiDiscrete([3, 3]); reward -distance, +1 and done on the goal; a noisy "wind" from the
    env's own RNG at every step (so restoring the RNG matters)."""

    def __init__(self, size: int = 5) -> None:
        self.size = size
        self.observation_space = spaces.Dict(
            {
                "pos": spaces.Box(0, size - 1, (2,), np.float32),
                "target": spaces.Dict({"xy": spaces.Box(0, size - 1, (2,), np.float32)}),
                "phase": spaces.Discrete(3, start=1),
            }
        )
        self.action_space = spaces.MultiDiscrete([3, 3])
        self.pos = np.zeros(2)
        self.goal = np.zeros(2)
        self.t = 0

    def _obs(self):
        return {
            "pos": self.pos.astype(np.float32),
            "target": {"xy": self.goal.astype(np.float32)},
            "phase": 1 + self.t % 3,
        }

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = self.np_random.integers(0, self.size, 2).astype(float)
        self.goal = self.np_random.integers(0, self.size, 2).astype(float)
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        move = np.asarray(action, dtype=float) - 1.0
        wind = self.np_random.normal(0.0, 0.1, 2)
        self.pos = np.clip(self.pos + move + wind, 0, self.size - 1)
        self.t += 1
        dist = float(np.abs(self.pos - self.goal).sum())
        reached = dist < 0.5
        return self._obs(), (1.0 if reached else -0.1 * dist), reached, False, {}

    def get_state(self):
        return {"pos": self.pos.copy(), "goal": self.goal.copy(), "t": self.t}

    def set_state(self, state):
        self.pos = np.asarray(state["pos"], dtype=float).copy()
        self.goal = np.asarray(state["goal"], dtype=float).copy()
        self.t = int(state["t"])


class NoStateWalk(gym.Env):
    """A 1-D walk on [-3, 3]: Discrete(3, start=-1) actions are the step; reward = -|x|; no
    get_state (resume restarts its episodes)."""

    observation_space = spaces.Box(-3.0, 3.0, (1,), np.float32)
    action_space = spaces.Discrete(3, start=-1)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = float(self.np_random.uniform(-3, 3))
        return np.array([self.x], np.float32), {}

    def step(self, action):
        assert action in (-1, 0, 1), action
        self.x = float(np.clip(self.x + 0.5 * int(action), -3, 3))
        return np.array([self.x], np.float32), -abs(self.x), False, False, {}


class WornTrack(gym.Env):
    """A 1-D track whose wear (like a Box2D world reused across resets) outlives its episodes: each
    step wears it, and the wear slows every later move; ``reset(seed=...)`` does not restore it."""

    observation_space = spaces.Box(-5.0, 5.0, (2,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self):
        self.wear = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.goal = (float(v) for v in self.np_random.uniform(-2, 2, size=2))
        return self._obs(), {}

    def _obs(self):
        return np.array([self.x, self.goal], np.float32)

    def step(self, action):
        self.wear += 1
        self.x = float(np.clip(self.x + 0.3 * float(action[0]) / (1 + 1e-3 * self.wear), -5, 5))
        return self._obs(), -abs(self.x - self.goal), False, False, {}


class Knobs(NoStateWalk):
    """A walk whose constructor takes ``size`` and ``speed``, and no ``render_mode``: it cannot
    render, and ``env.kwargs`` are checked against that signature."""

    def __init__(self, size: int = 3, speed: float = 0.5):
        self.size, self.speed = size, speed


class BadState(NoStateWalk):
    """A state protocol whose state a checkpoint cannot hold (an object inside)."""

    def get_state(self):
        return {"x": self.x, "sim": object()}

    def set_state(self, state):
        self.x = state["x"]


class Throttle(gym.Env):
    """Box actions with bounds that are neither symmetric nor [-1, 1] (``[0, 5]`` and ``[-3, 1]``),
    and a Dict observation of a Box, a Discrete (``start=1``) and a nested Dict: set the two
    actuators to targets that depend on the observation. Every action the env received is kept in
    ``received`` (tests read what reached the env)."""

    observation_space = spaces.Dict(
        {
            "speed": spaces.Box(-2.0, 2.0, (2,), np.float32),
            "gear": spaces.Discrete(3, start=1),
            "sensors": spaces.Dict({"load": spaces.Box(0.0, 1.0, (1,), np.float32)}),
        }
    )
    action_space = spaces.Box(
        np.array([0.0, -3.0], np.float32), np.array([5.0, 1.0], np.float32), dtype=np.float32
    )

    def __init__(self) -> None:
        self.received: list[np.ndarray] = []

    def _obs(self):
        return {
            "speed": self.speed.astype(np.float32),
            "gear": self.gear,
            "sensors": {"load": np.array([self.load], np.float32)},
        }

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.speed = self.np_random.uniform(-2, 2, 2)
        self.gear = int(self.np_random.integers(1, 4))
        self.load = float(self.np_random.uniform(0, 1))
        return self._obs(), {}

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        self.received.append(action.copy())
        target = np.array([1.5 * self.gear, -2.0 + 2.0 * self.load])
        reward = -float(np.square(action - target).sum())
        self.speed = np.clip(self.speed + 0.1 * (action - target), -2, 2)
        self.load = float(self.np_random.uniform(0, 1))
        return self._obs(), reward, False, False, {}


class _Refused(gym.Env):
    action_space = spaces.Box(-1, 1, (1,), np.float32)
    observation_space = spaces.Box(-1, 1, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


class ImageObs(_Refused):  # an image in no layout rlexp reads (rank 5)
    observation_space = spaces.Box(0, 255, (2, 2, 8, 8, 3), np.uint8)


class TextObs(_Refused):
    observation_space = spaces.Text(5)


class TupleAction(_Refused):
    action_space = spaces.Tuple((spaces.Discrete(2), spaces.Box(-1, 1, (1,), np.float32)))


for _name, _cls, _steps in (
    ("DictGoal-v0", DictGoal, 30),
    ("NoStateWalk-v0", NoStateWalk, 25),
    ("WornTrack-v0", WornTrack, 20),
    ("Knobs-v0", Knobs, 20),
    ("BadState-v0", BadState, 25),
    ("Throttle-v0", Throttle, 20),
    ("ImageObs-v0", ImageObs, 10),
    ("TextObs-v0", TextObs, 10),
    ("TupleAction-v0", TupleAction, 10),
):
    if _name not in gym.registry:
        gym.register(_name, entry_point=f"{__name__}:{_cls.__name__}", max_episode_steps=_steps)
