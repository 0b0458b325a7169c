"""``PickValid-v0``: a small Gymnasium task that needs action masking (issue #48), shipped with
rlexp (``env=pick_valid``, or ``env.name=rlexp.envs.pick_valid:PickValid-v0``).

Each step shows ``n_actions`` values in [0, 1] and which of the actions are valid now (1 to
``max_valid`` of them, drawn afresh every step). The valid action of the highest value earns 1, the
other valid ones 0; an invalid one ends the episode with ``penalty``. An episode lasts
``episode_steps`` steps at most.

The mask is ``info["action_mask"]`` (Gymnasium's convention, as Taxi's; the observation is the
values alone), or with ``mask_in=observation`` a ``Dict`` observation key ``action_mask`` next to
``values`` (``both``: the two). With masking the policy only learns to pick the best valid action (a random masked policy earns
~``0.61 * episode_steps`` with the defaults, the best ``episode_steps``); without it
(``env.action_mask=off``) the policy cannot tell valid from invalid actions (with ``mask_in=info``
its observation does not say) and most episodes end at their first or second step.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

ENV_ID = "PickValid-v0"


class PickValidEnv(gym.Env):
    """See the module's docstring."""

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self,
        n_actions: int = 6,
        max_valid: int = 3,
        episode_steps: int = 20,
        penalty: float = -1.0,
        mask_in: str = "info",
    ) -> None:
        if mask_in not in ("observation", "info", "both"):
            raise ValueError(f"env.kwargs.mask_in={mask_in!r}; choose from observation, info, both")
        if not 1 <= max_valid <= n_actions:
            raise ValueError(
                f"env.kwargs.max_valid={max_valid}; expected 1 to n_actions={n_actions}"
            )
        self.n, self.max_valid = int(n_actions), int(max_valid)
        self.episode_steps, self.penalty, self.mask_in = int(episode_steps), float(penalty), mask_in
        values = spaces.Box(0.0, 1.0, (self.n,), np.float32)
        if mask_in == "info":
            self.observation_space: spaces.Space = values
        else:
            mask = spaces.MultiBinary(self.n)
            self.observation_space = spaces.Dict({"values": values, "action_mask": mask})
        self.action_space = spaces.Discrete(self.n)
        self._t = 0
        self._values = np.zeros(self.n, np.float32)
        self._mask = np.ones(self.n, np.int8)

    def _draw(self) -> tuple[Any, dict]:
        rng = self.np_random
        self._values = rng.random(self.n).astype(np.float32)
        self._mask = np.zeros(self.n, np.int8)
        valid = rng.choice(self.n, size=int(rng.integers(1, self.max_valid + 1)), replace=False)
        self._mask[valid] = 1
        info = {"action_mask": self._mask.copy()} if self.mask_in != "observation" else {}
        if self.mask_in == "info":
            return self._values.copy(), info
        return {"values": self._values.copy(), "action_mask": self._mask.copy()}, info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._t = 0
        return self._draw()

    def step(self, action: Any):
        a = int(action)
        self._t += 1
        if not self._mask[a]:
            obs, info = self._draw()
            return obs, self.penalty, True, False, info
        best = float(self._values[self._mask.astype(bool)].max())
        reward = 1.0 if self._values[a] >= best else 0.0
        obs, info = self._draw()
        return obs, reward, False, self._t >= self.episode_steps, info


if ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=PickValidEnv)
