"""GridReach: a Gymnasium env of this project's own, trained by rlexp (``env.backend=gymnasium``).

An agent walks on a ``size`` x ``size`` grid to a goal cell. Both the start and the goal are drawn
from the env's ``np_random`` at every reset, so the seed decides the episodes. One step moves one
cell (right, up, left, down; a move into the border leaves the agent where it is).

- actions: ``Discrete(4)``;
- observations: ``Dict(goal=Box(2), position=Box(2))``, cell coordinates scaled to [0, 1] (rlexp
  flattens a Dict in sorted key order: ``goal`` then ``position``, 4 floats);
- reward: ``+1`` on reaching the goal (the episode terminates there), ``-0.01`` for every other
  step; ``TimeLimit`` of ``4 * size`` steps (``max_episode_steps`` at registration: 20 for the
  default 5 x 5 grid; another size can set ``env.max_episode_steps``);
- ``get_state()`` / ``set_state(state)``: the agent's and the goal's cells as plain data, so a
  checkpoint holds the env mid-episode and resume continues it exactly (rlexp also keeps the env's
  ``np_random`` and the ``TimeLimit`` counter).

Two names reach it from rlexp (only gymnasium and numpy are imported here, not rlexp):

- ``env.name=reach_lab.gridworld:GridReach-v0``: Gymnasium imports this module, which registers
  the id (``register()`` below runs at import);
- ``env.name=GridReach-v0``: with this package installed, rlexp's start-up loads the
  ``rlexp.plugins`` entry point (``reach_lab.plugin:register``), which registers it too.

Keyword arguments reach the constructor from ``env.kwargs`` (``gymnasium.make(id, **kwargs)``):
``env.kwargs.size=7``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

ENV_ID = "GridReach-v0"
#: The default grid's time limit: ``4 * size`` steps.
MAX_EPISODE_STEPS = 20

#: Action -> (dx, dy): right, up, left, down.
MOVES = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]], dtype=np.int64)
GOAL_REWARD = 1.0
STEP_COST = 0.01


class GridReach(gym.Env):
    """Walk from a random cell to a random goal cell of a ``size`` x ``size`` grid."""

    metadata = {"render_modes": ["ansi"], "render_fps": 4}

    def __init__(self, size: int = 5, render_mode: str | None = None) -> None:
        if int(size) != size or size < 2:
            raise ValueError(f"GridReach: size={size!r}; a grid needs a whole size >= 2")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"GridReach: render_mode={render_mode!r}; choose from ['ansi']")
        self.size = int(size)
        self.render_mode = render_mode
        self.action_space = spaces.Discrete(len(MOVES))
        cell = spaces.Box(0.0, 1.0, shape=(2,), dtype=np.float32)
        self.observation_space = spaces.Dict({"position": cell, "goal": cell})
        self._position = np.zeros(2, dtype=np.int64)
        self._goal = np.zeros(2, dtype=np.int64)

    # -- the dynamics ------------------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)  # seeds self.np_random when a seed is given
        cells = self.size * self.size
        start, goal = self.np_random.choice(cells, size=2, replace=False)  # never the same cell
        self._position = np.array(divmod(int(start), self.size), dtype=np.int64)
        self._goal = np.array(divmod(int(goal), self.size), dtype=np.int64)
        return self._obs(), {}

    def step(self, action: int) -> tuple[dict[str, np.ndarray], float, bool, bool, dict]:
        if not self.action_space.contains(action):
            raise ValueError(f"GridReach: action {action!r} is not in {self.action_space}")
        self._position = np.clip(self._position + MOVES[int(action)], 0, self.size - 1)
        reached = bool(np.array_equal(self._position, self._goal))
        reward = GOAL_REWARD if reached else -STEP_COST
        return self._obs(), reward, reached, False, {"is_success": reached}

    def _obs(self) -> dict[str, np.ndarray]:
        scale = np.float32(1.0 / (self.size - 1))
        return {
            "position": self._position.astype(np.float32) * scale,
            "goal": self._goal.astype(np.float32) * scale,
        }

    def render(self) -> str | None:
        if self.render_mode != "ansi":
            return None
        grid = [["."] * self.size for _ in range(self.size)]  # row 0 printed first: y = size-1
        for mark, (x, y) in (("G", self._goal), ("A", self._position)):
            grid[self.size - 1 - int(y)][int(x)] = mark
        return "\n".join("".join(row) for row in grid) + "\n"

    # -- checkpoints -------------------------------------------------------------------------------
    def get_state(self) -> dict[str, np.ndarray]:
        """Everything the next step depends on besides the RNG and the time limit (rlexp saves
        those itself), as plain data: a checkpoint cannot hold the env object."""
        return {"position": self._position.copy(), "goal": self._goal.copy()}

    def set_state(self, state: dict[str, np.ndarray]) -> None:
        """Put the env back where ``get_state()`` was taken (rlexp's resume calls it)."""
        position = np.asarray(state["position"], dtype=np.int64).reshape(2)
        goal = np.asarray(state["goal"], dtype=np.int64).reshape(2)
        for name, cell in (("position", position), ("goal", goal)):
            if cell.min() < 0 or cell.max() >= self.size:
                raise ValueError(
                    f"GridReach.set_state: {name} {cell.tolist()} is off the {self.size} x "
                    f"{self.size} grid (a state saved with another env.kwargs.size?)"
                )
        self._position, self._goal = position.copy(), goal.copy()


def register() -> None:
    """Register ``GridReach-v0`` with Gymnasium (once; a second call is a no-op)."""
    if ENV_ID not in gym.registry:
        gym.register(
            id=ENV_ID,
            entry_point="reach_lab.gridworld:GridReach",
            max_episode_steps=MAX_EPISODE_STEPS,
        )


register()  # at import: `env.name=reach_lab.gridworld:GridReach-v0` imports this module first
