"""Convert the composed DictConfig into typed dataclasses once, and check cross-field rules.

Below the entry point no code reads a DictConfig: it gets a ``RootConfig`` and its parts.
"""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from rlexp.config.schema import RootConfig


class ConfigError(ValueError):
    """A config value that cannot run; the message names the dotted key, the value and the fix."""


def to_root_config(cfg: DictConfig | dict[str, Any]) -> RootConfig:
    """Typed, validated config from Hydra's composed config (or a plain dict, e.g. a checkpoint's)."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.merge(OmegaConf.structured(RootConfig), cfg)
    config = OmegaConf.to_object(cfg)
    if not isinstance(config, RootConfig):
        raise ConfigError("the composed config does not use the rlexp_schema root schema")
    validate(config)
    return config


def to_dict(config: RootConfig) -> dict[str, Any]:
    """Plain-dict form of a config (for checkpoints, loggers and JSON)."""
    return OmegaConf.to_container(OmegaConf.structured(config), resolve=True)


def total_frames(config: RootConfig, world_size: int = 1) -> int:
    """Env steps to train for, summed over envs and processes (``iterations`` counts batches of
    ``frames_per_batch`` per process)."""
    t = config.trainer
    return (
        t.iterations * t.frames_per_batch * world_size
        if t.iterations is not None
        else t.total_frames
    )


def validate(config: RootConfig) -> None:
    """Cross-field rules that a schema alone cannot express."""
    t, e, a = config.trainer, config.env, config.algorithm
    if e.num_envs < 1:
        raise ConfigError(f"env.num_envs={e.num_envs} must be >= 1")
    if e.num_eval_envs < 0:
        raise ConfigError(f"env.num_eval_envs={e.num_eval_envs} must be >= 0")
    if t.frames_per_batch < e.num_envs or t.frames_per_batch % e.num_envs:
        raise ConfigError(
            f"trainer.frames_per_batch={t.frames_per_batch} must be a positive multiple of "
            f"env.num_envs={e.num_envs} (each env contributes frames_per_batch / num_envs steps)"
        )
    if t.iterations is not None and t.iterations < 1:
        raise ConfigError(
            f"trainer.iterations={t.iterations} must be >= 1 (or null to use total_frames)"
        )
    if total_frames(config) < 1:
        raise ConfigError(f"trainer.total_frames={t.total_frames} must be >= 1")
    if a.mini_batch_size < 1 or a.mini_batch_size > t.frames_per_batch:
        raise ConfigError(
            f"algorithm.mini_batch_size={a.mini_batch_size} must be in [1, trainer.frames_per_batch={t.frames_per_batch}]"
        )
    if a.num_epochs < 1:
        raise ConfigError(f"algorithm.num_epochs={a.num_epochs} must be >= 1")
    if not 0.0 <= a.gamma <= 1.0 or not 0.0 <= a.lmbda <= 1.0:
        raise ConfigError(
            f"algorithm.gamma={a.gamma} and algorithm.lmbda={a.lmbda} must be in [0, 1]"
        )
    if a.clip_epsilon <= 0:
        raise ConfigError(f"algorithm.clip_epsilon={a.clip_epsilon} must be > 0")
    if a.lr <= 0:
        raise ConfigError(f"algorithm.lr={a.lr} must be > 0")
    if str(a.compile).strip().lower() not in ("auto", "true", "false"):
        raise ConfigError(f"algorithm.compile={a.compile!r}; choose auto, true or false")
    if t.device != "auto" and not (t.device == "cpu" or t.device.startswith("cuda")):
        raise ConfigError(f"trainer.device={t.device!r}; choose auto, cpu, cuda or cuda:N")
    if t.torch_threads < 1:
        raise ConfigError(f"trainer.torch_threads={t.torch_threads} must be >= 1")
    from rlexp.envs.factory import BACKENDS

    if e.backend not in BACKENDS:
        raise ConfigError(f"env.backend={e.backend!r}; choose from {list(BACKENDS)}")
    if e.backend == "native" and e.native is None:
        raise ConfigError(
            f"env.backend=native needs env.native (env.name={e.name!r}); use env=push_cube or env=cart_pole"
        )
