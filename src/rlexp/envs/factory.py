"""``make_env``: one builder for every environment backend (docs/envs.md)."""

from __future__ import annotations

import logging

from torchrl.envs import EnvBase

from rlexp.config.rules import BACKENDS, RESCALE_BACKENDS
from rlexp.config.schema import EnvConfig

log = logging.getLogger(__name__)


def make_env(cfg: EnvConfig, num_envs: int, seed: int, device: str = "cpu") -> EnvBase:
    """Build ``num_envs`` batched copies of the configured task, seeded with ``seed``.

    ``device`` is where the CPU backends put their tensors (always ``cpu`` today); the batched torch
    backends (``vecenv``, ``torchrl``) are built on ``env.device`` instead: the env lives where its
    simulator does, and the policy follows ``trainer.device``."""
    images = (tuple(cfg.image_keys), cfg.frame_stack)  # the Gymnasium-shaped backends' images
    kept = tuple(cfg.observation_indices)  # the Box entries they keep (empty: all)
    masking = (cfg.action_mask, cfg.action_mask_key)  # where action masks come from (masks.py)
    if cfg.backend == "gymnasium":
        from rlexp.envs.gym import GymnasiumEnv

        env = GymnasiumEnv(
            cfg.name,
            num_envs,
            cfg.max_episode_steps,
            cfg.kwargs,
            device,
            *images,
            *masking,
            observation_indices=kept,
        )
    elif cfg.backend == "gymnasium_async":
        from rlexp.envs.gym_async import AsyncGymnasiumEnv

        env = AsyncGymnasiumEnv(
            cfg.name,
            num_envs,
            cfg.max_episode_steps,
            cfg.kwargs,
            *images,
            *masking,
            observation_indices=kept,
        )
    elif cfg.backend == "envpool":
        from rlexp.envs.envpool_env import EnvPoolEnv

        env = EnvPoolEnv(
            cfg.name,
            num_envs,
            seed,
            cfg.max_episode_steps,
            cfg.kwargs,
            cfg.num_threads,
            *images,
            kept,
        )
    elif cfg.backend == "native":
        from rlexp.envs.native import make_native_env

        if cfg.native is None:
            raise ValueError(
                f"env.backend=native needs an env.native term configuration (env.name={cfg.name!r}); "
                "use env=push_cube or env=cart_pole"
            )
        env = make_native_env(cfg.native, num_envs, seed, cfg.max_episode_steps, device=device)
    elif cfg.backend in ("vecenv", "torchrl"):
        from rlexp.envs.batched import make_batched_env

        env = make_batched_env(cfg, num_envs, seed)
    elif cfg.backend == "torchrl_gym":
        from rlexp.envs.gym import make_torchrl_gym_env

        env = make_torchrl_gym_env(cfg.name, num_envs, cfg.max_episode_steps, cfg.kwargs)
    else:
        raise ValueError(f"env.backend={cfg.backend!r} is not one of {list(BACKENDS)}")
    if cfg.rescale_actions and cfg.backend in RESCALE_BACKENDS:  # the Gymnasium-shaped adapters
        try:
            env.rescale_actions()
        except ValueError:
            env.close()
            raise
    env.set_seed(seed)
    return env
