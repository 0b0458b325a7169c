"""Tiny uint8-image Gymnasium envs for the image tests (``env.name=gym_image_envs:<Id>``; the
``gymnasium_async`` workers import this module by that name).

Every pixel of a frame is known in advance: ``frame(shape, t, episode)`` is ``arange`` over the
shape plus ``10 * t + 50 * episode`` (mod 256), so a test can build what the policy must see by
hand: the frame at step ``t`` of the copy's ``episode``-th episode (counted from 0 since the env
was made).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces


def frame(shape: tuple[int, ...], t: int, episode: int) -> np.ndarray:
    """The env's image at step ``t`` of episode ``episode``, as the env gives it (uint8)."""
    size = int(np.prod(shape))
    return ((np.arange(size) + 10 * t + 50 * episode) % 256).astype(np.uint8).reshape(shape)


class ImageEnv(gym.Env):
    """A uint8 image of ``shape`` (``dict_obs``: at ``cam/front``, with ``pos`` float32 [2] =
    [t, -t] and a grey ``depth`` [H, W] uint8 that only ``env.image_keys`` makes an image);
    Discrete(2) actions; episodes end (terminated) after ``length`` steps."""

    metadata = {"render_modes": []}

    def __init__(self, shape=(6, 5, 3), dict_obs: bool = False, length: int = 3) -> None:
        self.shape, self.dict_obs, self.length = tuple(shape), dict_obs, length
        image = spaces.Box(0, 255, self.shape, np.uint8)
        if dict_obs:
            self.observation_space = spaces.Dict(
                {
                    "cam": spaces.Dict({"front": image}),
                    "depth": spaces.Box(0, 255, (4, 7), np.uint8),
                    "pos": spaces.Box(-100, 100, (2,), np.float32),
                }
            )
        else:
            self.observation_space = image
        self.action_space = spaces.Discrete(2)
        self.t, self.episode = 0, -1

    def _obs(self):
        image = frame(self.shape, self.t, self.episode)
        if not self.dict_obs:
            return image
        return {
            "cam": {"front": image},
            "depth": frame((4, 7), self.t, self.episode),
            "pos": np.array([self.t, -self.t], dtype=np.float32),
        }

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.episode = 0, self.episode + 1
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        return self._obs(), float(self.t), self.t >= self.length, False, {}


class StatefulImageEnv(ImageEnv):
    """``ImageEnv`` (the Dict one) with ``get_state`` / ``set_state``: a checkpoint holds it exactly."""

    def __init__(self) -> None:
        super().__init__(dict_obs=True, length=4)

    def get_state(self):
        return {"t": self.t, "episode": self.episode}

    def set_state(self, state) -> None:
        self.t, self.episode = int(state["t"]), int(state["episode"])


class VectorEnv(ImageEnv):
    """No image: a float32 [3] observation (``env.frame_stack`` has nothing to stack)."""

    def __init__(self) -> None:
        super().__init__()
        self.observation_space = spaces.Box(-1, 1, (3,), np.float32)

    def _obs(self):
        return np.zeros(3, dtype=np.float32)


gym.register("Image-v0", entry_point=ImageEnv)
gym.register("ImageDict-v0", entry_point=ImageEnv, kwargs={"dict_obs": True})
gym.register("ImageRank5-v0", entry_point=ImageEnv, kwargs={"shape": (2, 2, 6, 5, 3)})
gym.register("ImageState-v0", entry_point=StatefulImageEnv)
gym.register("Vector-v0", entry_point=VectorEnv)
