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

import sys

import gymnasium as gym
import numpy as np


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
    torch = sys.modules.get("torch")  # (not imported here: gymnasium_async workers run without it)
    if torch is not None and isinstance(state, torch.Tensor):
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


def copy_state(env: gym.Env, kind: str, env_id: str) -> dict:
    """One copy's checkpoint entry: its RNG, whether it was reset, its time-limit counter, and its
    physics (``mujoco``) or ``get_state()`` (``state``); in the training process or in a
    gymnasium_async worker."""
    limit = time_limit(env)
    copy = {
        "rng": rng_state(env.unwrapped),
        "has_reset": has_reset(env),
        "elapsed_steps": -1  # no time limit, or not started
        if limit is None or limit._elapsed_steps is None
        else limit._elapsed_steps,
    }
    if kind == "mujoco":
        copy["physics"] = mujoco_state(env.unwrapped)
    elif kind == "state":
        copy["state"] = plain_state(env.unwrapped.get_state(), env_id)
    return copy


def restore_copy(env: gym.Env, copy: dict, kind: str) -> bool:
    """Put one copy back as ``copy_state`` saved it; False for a copy that had never been reset
    when it was saved (it is reset as usual)."""
    if not copy.get("has_reset", int(copy["elapsed_steps"]) >= 0):
        return False
    u = env.unwrapped
    if not has_reset(env):
        env.reset()  # gymnasium's OrderEnforcing wants a reset before step
    if kind == "mujoco":
        set_mujoco_state(u, copy["physics"])
    else:
        u.set_state(copy["state"])
    if copy.get("rng") is not None:
        u.np_random.bit_generator.state = copy["rng"]
    if time_limit(env) is not None and int(copy["elapsed_steps"]) >= 0:
        time_limit(env)._elapsed_steps = int(copy["elapsed_steps"])
    return True


#: ``resume_mode`` of a restored env, per kind.
RESTORED = {"mujoco": "restored (MuJoCo state)", "state": "restored (the env's get_state)"}


def restart_seed(sd: dict, base_seed: int | None, steps: int) -> int:
    """The seed of the new episodes a ``restart`` resume starts: from the checkpoint's seed (else
    ``base_seed``) and its step count, so the same checkpoint always restarts the same way."""
    base = sd.get("seed")
    base = base_seed if base is None else int(base)
    return ((0 if base is None else base) + 1_000_003 * steps) % 2**31


def restart_mode(
    seed: int,
    saved_kind: str,
    state_kind: str,
    no_state: str = "the env offers no get_state()/set_state()",
) -> str:
    """``resume_mode`` of a restart: the seed and why the episodes could not continue
    (``no_state``: why this env holds no state, where its kind is ``restart``)."""
    if saved_kind == state_kind:
        why = no_state
    elif saved_kind == "restart":
        why = "the checkpoint holds no env state (get_state() failed when it was saved)"
    else:
        why = f"the checkpoint holds a {saved_kind!r} env state, this env's is {state_kind!r}"
    return f"restarted (new episodes seeded {seed}: {why})"
