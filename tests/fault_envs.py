"""User envs that misbehave on purpose (#43), registered when this module is imported, so tests name
them as ``env.name=fault_envs:<Id>``. Each is a 1-D walk: Box(3,) observations, a Box(1,) action,
a step counter; what goes wrong is chosen by its kwargs.

- ``Walk-v0``: ``kill_at=N`` SIGKILLs its own process at its N-th step (as the OOM killer would),
  once per ``marker`` file; ``exit_at=N`` raises ``raise_what`` (``exit0``: ``sys.exit(0)``,
  ``keyboard``: ``KeyboardInterrupt``, ``memory``: numpy's ``_ArrayMemoryError``) at its N-th step,
  ``exit_in`` chooses ``step``, ``reset`` or ``close`` (its first close, once it was reset
  ``exit_at`` times); ``bad_set_state`` (or ``FAULT_ENVS_BAD_SET_STATE=1``): ``set_state`` raises.
  ``interrupt_marker``: its 2nd construction gets a Ctrl-C and fails (a build that a Ctrl-C broke).
  ``FAULT_ENVS_EXIT_IN_RESET=1``: every ``reset`` calls ``sys.exit(0)``.
  ``endless``: episodes never end (registered without a time limit: ``Endless-v0``).
"""

from __future__ import annotations

import os
import signal
import sys

import gymnasium as gym
import numpy as np
from gymnasium import spaces

#: The tests' tiny run on ``Walk-v0``: 512 steps in 128-step iterations, a checkpoint each, no eval.
TINY_RUN = {
    "env": "hopper",
    "env.name": "fault_envs:Walk-v0",
    "env.num_envs": "1",
    "trainer.total_frames": "512",
    "trainer.frames_per_batch": "128",
    "trainer.save_every": "128",
    "trainer.eval_every": "0",
    "algorithm.num_epochs": "1",
    "algorithm.compile": "false",
    "logger": "none",
    "trainer.progress": "false",
}


def tiny_run(*changes: str) -> list[str]:
    """TINY_RUN's overrides with ``changes`` (``key=value``) replacing a key's value or added."""
    run = dict(TINY_RUN)
    for change in changes:
        key, value = change.split("=", 1)
        run[key] = value
    return [f"{key}={value}" for key, value in run.items()]


def _raise(what: str) -> None:
    if what == "exit0":
        sys.exit(0)
    if what == "keyboard":
        raise KeyboardInterrupt
    if what == "memory":
        np.zeros((2**24, 2**24), dtype=np.float64)  # numpy's _ArrayMemoryError (shape, dtype)
    raise RuntimeError(f"unknown raise_what {what!r}")


class Walk(gym.Env):
    def __init__(
        self,
        kill_at: int = 0,
        marker: str = "",
        exit_at: int = 0,
        exit_in: str = "step",
        raise_what: str = "exit0",
        bad_set_state: bool = False,
        endless: bool = False,
        episode: int = 20,
        interrupt_marker: str = "",
    ) -> None:
        if interrupt_marker:  # the 1st build (the config check) passes, the 2nd is interrupted
            if os.path.exists(interrupt_marker):
                os.kill(os.getpid(), signal.SIGINT)  # the terminal's Ctrl-C reached this process
                raise RuntimeError("a worker the Ctrl-C reached died (simulated)")
            open(interrupt_marker, "w").close()
        self.observation_space = spaces.Box(-np.inf, np.inf, (3,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.kill_at, self.marker = int(kill_at), str(marker)
        self.exit_at, self.exit_in, self.raise_what = int(exit_at), exit_in, raise_what
        self.bad_set_state, self.endless, self.episode = bad_set_state, endless, int(episode)
        self.x, self.t, self.steps, self.resets, self.closes = 0.0, 0, 0, 0, 0

    def _obs(self) -> np.ndarray:
        return np.array([self.x, self.t / 10.0, 1.0], dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.resets += 1
        if os.environ.get("FAULT_ENVS_EXIT_IN_RESET") == "1":
            sys.exit(0)
        if self.exit_in == "reset" and self.exit_at and self.resets >= self.exit_at:
            _raise(self.raise_what)
        self.x, self.t = float(self.np_random.uniform(-0.5, 0.5)), 0
        return self._obs(), {}

    def step(self, action):
        self.steps += 1
        if self.kill_at and self.steps >= self.kill_at and not os.path.exists(self.marker):
            open(self.marker, "w").close()  # once: the re-run resumes past it
            os.kill(os.getpid(), signal.SIGKILL)
        if self.exit_in == "step" and self.exit_at and self.steps >= self.exit_at:
            _raise(self.raise_what)
        self.x = float(np.clip(self.x + 0.1 * float(np.asarray(action).reshape(-1)[0]), -2, 2))
        self.t += 1
        done = (not self.endless) and self.t >= self.episode
        return self._obs(), -abs(self.x), done, False, {}

    def close(self):
        closes, self.closes = self.closes, self.closes + 1
        if self.exit_in == "close" and self.exit_at and self.resets >= self.exit_at and not closes:
            _raise(self.raise_what)
        super().close()

    def get_state(self):
        return {"x": self.x, "t": self.t}

    def set_state(self, state):
        if self.bad_set_state or os.environ.get("FAULT_ENVS_BAD_SET_STATE") == "1":
            raise ValueError("set_state: the saved walk does not fit this one")
        self.x, self.t = float(state["x"]), int(state["t"])


gym.register("Walk-v0", entry_point=Walk)
gym.register("Endless-v0", entry_point=Walk, kwargs={"endless": True})
