"""How a checkpoint holds a Gymnasium env mid-episode, as plain data (never the env object).

Three kinds (``env_state_kind``; docs/envs.md, "Checkpoints and resume"):

- ``state``: the env defines ``get_state()`` and ``set_state(state)`` (on its unwrapped class);
  ``get_state`` returns plain data (numpy arrays, numbers, strings, lists, tuples, dicts), and
  ``set_state`` puts the env back exactly there. Resume continues the episode.
- ``mujoco``: a Gymnasium MuJoCo env: its integration state (``mj_getState``), bit-exact.
- ``restart``: anything else: on resume every copy starts a new episode, seeded from the checkpoint.

With each copy go its RNG (``np_random``) and its ``TimeLimit`` counter.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch


def env_state_kind(env: gym.Env) -> str:
    """How a checkpoint can hold ``env`` mid-episode: ``state`` (the env defines ``get_state`` and
    ``set_state``), ``mujoco`` (a Gymnasium MuJoCo env), else ``restart``."""
    u = env.unwrapped
    if callable(getattr(u, "get_state", None)) and callable(getattr(u, "set_state", None)):
        return "state"
    model, data = getattr(u, "model", None), getattr(u, "data", None)
    if model is not None and data is not None and type(model).__module__.startswith("mujoco"):
        return "mujoco"
    return "restart"


#: What ``get_state()`` may return: what ``torch.load(weights_only=True)`` reads back.
_PLAIN = (bool, int, float, str, bytes, type(None))


def plain_state(state: object, env_id: str, where: str = "get_state()") -> object:
    """``state`` as checkpointable plain data (numpy arrays, numbers, strings, lists, tuples and
    dicts of them); a TypeError naming the env and the path of anything else."""
    if isinstance(state, _PLAIN):
        return state
    if isinstance(state, np.generic):
        return state.item()
    if isinstance(state, np.ndarray):
        if state.dtype == object:
            raise TypeError(f"env.name={env_id!r}: {where} holds an object array; use plain arrays")
        return state.copy()
    if isinstance(state, torch.Tensor):
        return state.detach().cpu().clone()
    if isinstance(state, dict):
        return {k: plain_state(v, env_id, f"{where}[{k!r}]") for k, v in state.items()}
    if isinstance(state, list | tuple):
        return type(state)(plain_state(v, env_id, f"{where}[{i}]") for i, v in enumerate(state))
    raise TypeError(
        f"env.name={env_id!r}: {where} is a {type(state).__name__}; a checkpoint holds only plain "
        "data (numpy arrays, numbers, strings, lists, tuples, dicts): docs/envs.md"
    )


def rng_state(u: gym.Env) -> dict | None:
    rng = getattr(u, "_np_random", None)  # None until the env first draws (no RNG to keep)
    return None if rng is None else rng.bit_generator.state


def mujoco_state(u: gym.Env) -> np.ndarray:
    import mujoco

    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    state = np.empty(mujoco.mj_stateSize(u.model, spec))
    mujoco.mj_getState(u.model, u.data, state, spec)
    return state


def set_mujoco_state(u: gym.Env, physics: np.ndarray) -> None:
    import mujoco

    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    mujoco.mj_setState(u.model, u.data, np.asarray(physics, dtype=np.float64), spec)
    mujoco.mj_forward(u.model, u.data)


def time_limit(env: gym.Env) -> gym.wrappers.TimeLimit | None:
    while isinstance(env, gym.Wrapper):
        if isinstance(env, gym.wrappers.TimeLimit):
            return env
        env = env.env
    return None


def has_reset(env: gym.Env) -> bool:
    while isinstance(env, gym.Wrapper):
        if isinstance(env, gym.wrappers.OrderEnforcing):
            return env.has_reset
        env = env.env
    return True
