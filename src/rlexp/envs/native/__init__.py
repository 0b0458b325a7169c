"""Native batched MuJoCo tasks (PushCube, CartPole) as TorchRL envs, built from term configurations.

``make_native_env(task_cfg, num_envs, seed)`` is the one entry point; ``TASKS`` lists the scenes and
``OBSERVATIONS`` / ``REWARDS`` / ``EVENTS`` / ``ACTIONS`` the term functions a config can name.
See docs/native_tasks.md.
"""

from __future__ import annotations

from rlexp.envs.native.render import choose_gl_backend

choose_gl_backend()  # before mujoco is imported below, so mujoco.Renderer picks it up

import torch  # noqa: E402
from torchrl.envs import EnvBase  # noqa: E402

from rlexp.config.native_task import NativeTaskConfig  # noqa: E402
from rlexp.envs.native.actions import ACTIONS  # noqa: E402
from rlexp.envs.native.env import NativeEnv  # noqa: E402
from rlexp.envs.native.events import EVENTS  # noqa: E402
from rlexp.envs.native.observations import OBSERVATIONS  # noqa: E402
from rlexp.envs.native.rewards import REWARDS  # noqa: E402
from rlexp.envs.native.tasks import TASKS, TaskSpec, default_task_config, get_task  # noqa: E402

__all__ = [
    "ACTIONS",
    "EVENTS",
    "OBSERVATIONS",
    "REWARDS",
    "TASKS",
    "NativeEnv",
    "TaskSpec",
    "default_task_config",
    "get_task",
    "make_native_env",
]


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
    env = NativeEnv(
        task, num_envs, max_episode_steps=max_episode_steps, device=device, num_threads=num_threads
    )
    env.set_seed(seed)
    return env
