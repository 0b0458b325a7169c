"""rlexp's batched native tasks (``NativeEnv``) behind the vector-env APIs of other libraries.

- ``NativeVectorEnv``: a ``gymnasium.vector.VectorEnv`` with ``AutoresetMode.SAME_STEP``: a finished
  env is reset inside ``step``, the observation returned is the fresh one, and the true final
  observation is in ``infos["final_obs"]`` (``infos["_final_obs"]`` marks which) — what the
  CleanRL-style baseline (``benchmarks/cleanrl_ppo.py``) consumes.
- ``NativeVecEnv``: a Stable-Baselines3 ``VecEnv``; finished envs carry ``terminal_observation`` and
  ``TimeLimit.truncated`` in their info dicts, so SB3 bootstraps truncated episodes.

Both drive the env through ``step_action`` / ``autoreset_observation``, the same two calls rlexp's
own collector makes, so every contender pays the same env cost.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch


def _spaces(env) -> tuple[gym.spaces.Box, gym.spaces.Box]:
    """Single-env observation and action boxes of a batched rlexp env."""
    obs_dim = int(env.observation_spec["observation"].shape[-1])
    act_dim = int(env.action_spec.shape[-1])
    low = env.action_spec.space.low.reshape(-1, act_dim)[0].numpy().astype(np.float32)
    high = env.action_spec.space.high.reshape(-1, act_dim)[0].numpy().astype(np.float32)
    obs_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
    return obs_space, gym.spaces.Box(low, high, (act_dim,), np.float32)


def _step(env, actions: np.ndarray):
    """(obs to continue from, reward, terminated, truncated, true final obs) as numpy arrays."""
    nxt = env.step_action(torch.as_tensor(actions, dtype=torch.float32))
    final = nxt.get("observation").numpy()
    obs = env.autoreset_observation(nxt).numpy()
    reward = nxt.get("reward").numpy().reshape(-1)
    term = nxt.get("terminated").numpy().reshape(-1)
    trunc = nxt.get("truncated").numpy().reshape(-1)
    return obs, reward, term, trunc, final


class NativeVectorEnv(gym.vector.VectorEnv):
    """A Gymnasium vector env (same-step autoreset) over one batched rlexp env."""

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP}

    def __init__(self, env) -> None:
        self.env = env
        self.num_envs = int(env.batch_size.numel())
        self.single_observation_space, self.single_action_space = _spaces(env)
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, self.num_envs
        )
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self.env.set_seed(seed)
        return self.env.reset().get("observation").numpy(), {}

    def step(self, actions: np.ndarray):
        obs, reward, term, trunc, final = _step(self.env, actions)
        done = term | trunc
        infos: dict[str, Any] = {}
        if done.any():
            infos = {"final_obs": final, "_final_obs": done}
        return obs, reward, term, trunc, infos

    def close(self, **kwargs: Any) -> None:
        self.env.close()


def make_sb3_vec_env(env):
    """An SB3 ``VecEnv`` over one batched rlexp env (SB3 imported only here)."""
    from stable_baselines3.common.vec_env import VecEnv

    class NativeVecEnv(VecEnv):
        """SB3's vectorised-env interface over ``NativeEnv`` (auto-reset inside ``step_wait``)."""

        def __init__(self, env) -> None:
            self.env = env
            self.render_mode = None
            obs_space, act_space = _spaces(env)
            super().__init__(int(env.batch_size.numel()), obs_space, act_space)
            self._actions: np.ndarray | None = None

        def reset(self):
            if self._seeds[0] is not None:
                self.env.set_seed(self._seeds[0])
            self._reset_seeds()
            return self.env.reset().get("observation").numpy()

        def step_async(self, actions: np.ndarray) -> None:
            self._actions = actions

        def step_wait(self):
            obs, reward, term, trunc, final = _step(self.env, self._actions)
            done = term | trunc
            infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
            for i in np.flatnonzero(done):
                infos[i]["terminal_observation"] = final[i]
                infos[i]["TimeLimit.truncated"] = bool(trunc[i] and not term[i])
            return obs, reward, done, infos

        def close(self) -> None:
            self.env.close()

        def get_attr(self, attr_name: str, indices=None) -> list[Any]:
            return [getattr(self, attr_name, None) for _ in self._get_indices(indices)]

        def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
            setattr(self, attr_name, value)

        def env_method(self, method_name: str, *args, indices=None, **kwargs) -> list[Any]:
            raise NotImplementedError(f"NativeVecEnv has no per-env method {method_name!r}")

        def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
            return [False for _ in self._get_indices(indices)]

    return NativeVecEnv(env)
