"""``make_env``: one builder for every environment backend."""

from __future__ import annotations

import logging

from torchrl.envs import EnvBase

from rlexp.config.rules import BACKENDS
from rlexp.config.schema import EnvConfig

log = logging.getLogger(__name__)


def make_env(cfg: EnvConfig, num_envs: int, seed: int, device: str = "cpu") -> EnvBase:
    """Build ``num_envs`` batched copies of the configured task, seeded with ``seed``."""
    if cfg.backend == "gymnasium":
        from rlexp.envs.gym import GymnasiumEnv

        env = GymnasiumEnv(cfg.name, num_envs, cfg.max_episode_steps, cfg.kwargs, device=device)
    elif cfg.backend == "native":
        from rlexp.envs.native import make_native_env

        if cfg.native is None:
            raise ValueError(
                f"env.backend=native needs an env.native term configuration (env.name={cfg.name!r}); "
                "use env=push_cube or env=cart_pole"
            )
        env = make_native_env(cfg.native, num_envs, seed, cfg.max_episode_steps, device=device)
    elif cfg.backend == "torchrl_gym":
        from rlexp.envs.gym import make_torchrl_gym_env

        env = make_torchrl_gym_env(cfg.name, num_envs, cfg.max_episode_steps, cfg.kwargs)
    else:
        raise ValueError(f"env.backend={cfg.backend!r} is not one of {list(BACKENDS)}")
    env.set_seed(seed)
    return env
