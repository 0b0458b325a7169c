"""Gymnasium MuJoCo tasks as batched TorchRL environments.

``GymnasiumEnv`` is a lean ``EnvBase`` over ``num_envs`` Gymnasium copies: specs come from TorchRL's
own space conversion, observations are cast to float32, actions are clipped to the action box, and
a finished copy is reset inside ``_step`` (its true final observation goes to ``"next"`` so truncated
episodes bootstrap correctly; the following masked ``_reset`` hands back the cached reset
observation). It exists because TorchRL's ``GymEnv`` + ``DoubleToFloat`` costs ~0.4 ms of Python per
step here (measured: 1,065 steps/s for collection alone on HalfCheetah-v5 against 15,000 for raw
Gymnasium); ``env.backend=torchrl_gym`` still builds that reference path.
"""

from __future__ import annotations

import logging
import os

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

log = logging.getLogger(__name__)

#: The Gymnasium MuJoCo suite (any other registered id works too; these are the tested ones).
GYM_MUJOCO_TASKS = (
    "HalfCheetah-v5",
    "Hopper-v5",
    "Walker2d-v5",
    "Ant-v5",
    "InvertedPendulum-v5",
    "InvertedDoublePendulum-v5",
    "Humanoid-v5",
    "Swimmer-v5",
    "Reacher-v5",
)


def check_gym_id(env_id: str) -> None:
    """Raise a KeyError naming close matches when ``env_id`` is not a registered Gymnasium id."""
    if env_id in gym.registry:
        return
    import difflib

    close = difflib.get_close_matches(env_id, list(gym.registry), n=3)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    raise KeyError(
        f"env.name={env_id!r} is not a registered Gymnasium environment; "
        f"MuJoCo tasks: {list(GYM_MUJOCO_TASKS)}{hint}"
    )


class GymnasiumEnv(EnvBase):
    """``num_envs`` copies of a Gymnasium env stepped in one process, as one TorchRL env."""

    def __init__(
        self,
        env_id: str,
        num_envs: int = 1,
        max_episode_steps: int | None = None,
        make_kwargs: dict | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        check_gym_id(env_id)
        os.environ.setdefault("MUJOCO_GL", "egl")
        kwargs = dict(make_kwargs or {})
        if max_episode_steps is not None:
            kwargs["max_episode_steps"] = max_episode_steps
        self.env_id = env_id
        self.num_envs = num_envs
        self._envs = [gym.make(env_id, **kwargs) for _ in range(num_envs)]
        obs_space = self._envs[0].observation_space
        act_space = self._envs[0].action_space
        if not isinstance(act_space, gym.spaces.Box) or not isinstance(obs_space, gym.spaces.Box):
            raise TypeError(
                f"env.name={env_id!r}: rlexp's PPO needs Box observation and action spaces, got "
                f"{type(obs_space).__name__} / {type(act_space).__name__}"
            )
        super().__init__(batch_size=torch.Size([num_envs]), device=device)
        self.obs_dim = int(np.prod(obs_space.shape))
        self.act_dim = int(np.prod(act_space.shape))
        self._low = act_space.low.astype(np.float64).reshape(-1)
        self._high = act_space.high.astype(np.float64).reshape(-1)
        n = num_envs
        self.observation_spec = Composite(
            observation=Unbounded(shape=(n, self.obs_dim), dtype=torch.float32, device=self.device),
            shape=(n,),
            device=self.device,
        )
        self.action_spec = Bounded(
            low=torch.as_tensor(self._low, dtype=torch.float32).expand(n, self.act_dim).clone(),
            high=torch.as_tensor(self._high, dtype=torch.float32).expand(n, self.act_dim).clone(),
            shape=(n, self.act_dim),
            dtype=torch.float32,
            device=self.device,
        )
        self.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            done=Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device),
            terminated=Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device),
            truncated=Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device),
            shape=(n,),
            device=self.device,
        )
        self._seed: int | None = None
        self._reset_obs = np.zeros((n, self.obs_dim), dtype=np.float32)
        self._pending_reset = np.zeros(n, dtype=bool)

    # -- TorchRL API -------------------------------------------------------------------------------
    def _set_seed(self, seed: int | None) -> None:
        self._seed = seed
        for i, env in enumerate(self._envs):
            env.action_space.seed(None if seed is None else seed + i)

    def _reset_one(self, i: int) -> np.ndarray:
        if self._seed is not None:
            # Seed each copy once; later resets continue its own RNG stream.
            obs, _ = self._envs[i].reset(seed=self._seed + i)
        else:
            obs, _ = self._envs[i].reset()
        return obs

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(-1).cpu().numpy()
        obs = np.empty((self.num_envs, self.obs_dim), dtype=np.float32)
        for i in range(self.num_envs):
            if mask is not None and not mask[i]:
                continue
            if mask is not None and self._pending_reset[i]:
                obs[i] = self._reset_obs[i]  # already reset inside _step
            else:
                obs[i] = self._reset_one(i)
            self._pending_reset[i] = False
        if self._seed is not None and mask is None:
            self._seed = None  # seeded once: further resets draw from each env's own stream
        return TensorDict(
            {"observation": torch.from_numpy(obs)}, batch_size=self.batch_size, device=self.device
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        actions = tensordict.get("action").detach().cpu().numpy().astype(np.float64)
        np.clip(actions, self._low, self._high, out=actions)
        n = self.num_envs
        obs = np.empty((n, self.obs_dim), dtype=np.float32)
        reward = np.empty((n, 1), dtype=np.float32)
        terminated = np.zeros((n, 1), dtype=bool)
        truncated = np.zeros((n, 1), dtype=bool)
        for i, env in enumerate(self._envs):
            o, r, term, trunc, _ = env.step(actions[i])
            obs[i] = o
            reward[i, 0] = r
            terminated[i, 0] = term
            truncated[i, 0] = trunc
            if term or trunc:
                self._reset_obs[i] = self._reset_one(i)
                self._pending_reset[i] = True
        return TensorDict(
            {
                "observation": torch.from_numpy(obs),
                "reward": torch.from_numpy(reward),
                "done": torch.from_numpy(terminated | truncated),
                "terminated": torch.from_numpy(terminated),
                "truncated": torch.from_numpy(truncated),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    # -- extras ------------------------------------------------------------------------------------
    def render(self, env_id: int = 0) -> np.ndarray:
        """An RGB frame of copy ``env_id`` (needs ``render_mode='rgb_array'`` in ``env.kwargs``)."""
        return self._envs[env_id].render()

    def close(self, *, raise_if_closed: bool = True) -> None:
        for env in self._envs:
            env.close()
        super().close(raise_if_closed=raise_if_closed)


def make_torchrl_gym_env(env_id: str, num_envs: int, max_episode_steps: int | None, make_kwargs: dict):
    """The reference path: TorchRL's own ``GymEnv`` with a float32 cast (slower per step)."""
    from torchrl.envs import DoubleToFloat, GymEnv, TransformedEnv

    check_gym_id(env_id)
    kwargs = dict(make_kwargs)
    if max_episode_steps is not None:
        kwargs["max_episode_steps"] = max_episode_steps
    if num_envs > 1:
        from torchrl.envs import SerialEnv

        base = SerialEnv(num_envs, lambda: GymEnv(env_id, **kwargs))
    else:
        base = GymEnv(env_id, **kwargs)
    return TransformedEnv(base, DoubleToFloat())
