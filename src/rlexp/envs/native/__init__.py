"""Native batched MuJoCo tasks (PushCube, CartPole) as TorchRL envs, built from term configurations.

``make_native_env(task_cfg, num_envs, seed)`` is the one entry point; ``TASKS`` lists the scenes and
``OBSERVATIONS`` / ``REWARDS`` / ``EVENTS`` / ``ACTIONS`` the term functions a config can name.
See docs/native_tasks.md.

Importing this package only chooses the GL backend (``MUJOCO_GL``, before anything imports MuJoCo);
the names above are imported when first used, so that ``rlexp.envs.native.render`` can be asked
whether offscreen rendering can work without importing MuJoCo, torch or TorchRL.

Part of ``envs`` (layer 2). May import: layers 0-1 (``config.native_task``) and the other pieces.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from rlexp.envs.native.render import choose_gl_backend

choose_gl_backend()  # before mujoco is imported, so mujoco.Renderer picks it up

if TYPE_CHECKING:
    import torch
    from torchrl.envs import EnvBase

    from rlexp.config.native_task import NativeTaskConfig

#: public name -> the module that defines it (imported on first use)
_LAZY = {
    "ACTIONS": "rlexp.envs.native.actions",
    "EVENTS": "rlexp.envs.native.events",
    "OBSERVATIONS": "rlexp.envs.native.observations",
    "REWARDS": "rlexp.envs.native.rewards",
    "TASKS": "rlexp.envs.native.tasks",
    "TaskSpec": "rlexp.envs.native.tasks",
    "default_task_config": "rlexp.envs.native.tasks",
    "get_task": "rlexp.envs.native.tasks",
    "NativeEnv": "rlexp.envs.native.env",
}

__all__ = [*sorted(_LAZY), "make_native_env"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def make_native_env(
    task: NativeTaskConfig,
    num_envs: int,
    seed: int,
    max_episode_steps: int | None = None,
    device: str | torch.device = "cpu",
    num_threads: int | None = None,
) -> EnvBase:
    """Build ``num_envs`` copies of the native task ``task.task`` with its terms, seeded with ``seed``.

    ``max_episode_steps`` overrides the task's time limit; ``num_threads`` the physics thread pool
    (default: one thread per core for 4+ envs).
    """
    from rlexp.envs.native.env import NativeEnv

    env = NativeEnv(
        task, num_envs, max_episode_steps=max_episode_steps, device=device, num_threads=num_threads
    )
    env.set_seed(seed)
    return env
