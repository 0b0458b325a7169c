"""How the built-in events reach into an env: under its TorchRL transforms, per-env MuJoCo models,
the native tasks' own event functions, and a fresh observation after an event moved something.

Works with both kinds of MuJoCo env rlexp builds: the native batched tasks (``rlexp.envs.native``)
and the Gymnasium adapter (one Gymnasium env per copy).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import numpy as np

from rlexp.config.native_task import check_params
from rlexp.events.manager import EventContext


def event_env_ids(ctx: EventContext) -> np.ndarray:
    """The ids of the envs an event concerns: ``ctx.env_ids``, or every env when it is None."""
    n = int(ctx.env.batch_size.numel())
    return (
        np.arange(n) if ctx.env_ids is None else np.asarray(ctx.env_ids, dtype=np.int64).reshape(-1)
    )


def base_env(env: Any) -> Any:
    """The env under TorchRL transforms."""
    while hasattr(env, "base_env"):
        env = env.base_env
    return env


def env_model(env: Any, i: int, private: bool):
    """Env ``i``'s MuJoCo model; ``private``: give a batched native env its own copy first."""
    if hasattr(env, "_models"):  # native batched env: one model per env in its rollout list
        if private and env._models[i] is env.model:
            env._models[i] = copy.copy(env.model)
        return env._models[i]
    if hasattr(env, "_envs"):  # GymnasiumEnv: each copy owns its model
        return env._envs[i].unwrapped.model
    raise TypeError(f"{type(env).__name__} exposes no MuJoCo models to randomise")


def nominal_model(env: Any):
    """The MuJoCo model every copy of the env was built from (before any randomisation)."""
    if hasattr(env, "_models"):
        return env.model
    model = getattr(getattr(env, "_envs", [None])[0], "unwrapped", None)
    model = getattr(model, "model", None)
    if model is None or not type(model).__module__.startswith("mujoco"):
        name = getattr(env, "env_id", None)
        what = f"env.name={name!r}" if name else type(env).__name__
        backend = getattr(env, "backend", "gymnasium")
        if backend != "gymnasium":  # the models live in worker processes or EnvPool's C++
            raise TypeError(
                f"{what} (env.backend={backend}) exposes no MuJoCo model to the training process "
                "(events that change physics need one: env.backend=gymnasium)"
            )
        raise TypeError(f"{what} has no MuJoCo model (events that change physics need one)")
    return model


def native_event(name: str):
    """The native task event function registered as ``name`` (``rlexp.envs.native.EVENTS``)."""
    from rlexp.envs.native import EVENTS

    return EVENTS.get(name)


def native_check_env(native_name: str) -> Callable[..., None]:
    """``check_env`` of a built-in event that runs the native task event ``native_name``: the env
    is a native task and the params name its objects."""

    def check_env(env: Any, where: str, num_envs: int | None = None, **params: Any) -> None:
        base = base_env(env)
        if not hasattr(base, "object_pose"):
            raise TypeError(
                f"{where}: {native_name} moves objects of the native tasks (env=push_cube); "
                f"this env is {type(base).__name__}"
            )
        func = native_event(native_name)
        check_params(native_name, params, func.PARAMS, f"{where}.params", env=base)

    return check_env


def refresh_observation(env: Any) -> None:
    """Recompute a native env's current observation after its state was changed from outside."""
    if hasattr(env, "_observation_dict"):
        env._v.current_obs = env._flatten(env._observation_dict())
