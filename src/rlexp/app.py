"""Entry point: Hydra composes ``conf/``, ``train(config, run_dir)`` builds the objects and runs.

``main()`` is what ``python train.py`` and ``rlexp train`` call. Heavy libraries (torch, torchrl)
are imported only once the config has composed and validated, so a bad override fails in a second.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from rlexp.config.schema import RootConfig, register_configs
from rlexp.config.validate import ConfigError, to_dict, to_root_config, total_frames

log = logging.getLogger(__name__)

#: The repository's ``conf/`` (the package is installed in editable mode from the repository).
CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


def resolve_device(device: str, strict: bool = False) -> str:
    """``auto`` -> ``cuda`` when a GPU is visible, else ``cpu``; CUDA asked on a CPU-only machine
    falls back to CPU with one warning unless ``strict``."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        if strict:
            raise ConfigError(
                f"trainer.device={device!r} but CUDA is not available on this machine "
                "(trainer.strict_device=true); use trainer.device=auto or cpu"
            )
        log.warning("trainer.device=%r but CUDA is not available: running on cpu", device)
        return "cpu"
    return device


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (the envs are seeded where they are built)."""
    import random

    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def train(config: RootConfig, run_dir: Path) -> dict[str, float]:
    """Build envs, policy, PPO, loggers and Trainer from ``config``; train; return the last eval."""
    import torch

    from rlexp import _speedups
    from rlexp.algorithms.ppo import make_algorithm
    from rlexp.envs.factory import make_env
    from rlexp.events import EventManager
    from rlexp.logging import make_logger
    from rlexp.policies.actor_critic import make_policy
    from rlexp.trainer import Trainer

    t, e = config.trainer, config.env
    _speedups.apply()
    torch.set_num_threads(t.torch_threads)
    device = resolve_device(t.device, t.strict_device)
    seed_everything(config.seed)
    run_dir.mkdir(parents=True, exist_ok=True)
    t.device = device  # the saved config records the device actually used
    config_dict = to_dict(config)
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(config_dict)))
    log.info("run dir: %s (device %s, seed %d)", run_dir, device, config.seed)

    env = make_env(e, e.num_envs, config.seed)
    eval_env = make_env(e, e.num_eval_envs, config.seed + 1_000_000) if e.num_eval_envs > 0 else None
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    log.info("env %s x%d: obs %d, action %d", e.name, e.num_envs, obs_dim, act_dim)
    policy = make_policy(config.policy, obs_dim, act_dim, env.action_spec, e.normalize_observations,
                         e.clip_observations).to(device)
    total = total_frames(config)
    iterations = -(-total // t.frames_per_batch)
    algorithm = make_algorithm(config.algorithm, policy, iterations)
    logger = make_logger(config.logger, run_dir, t.exp_name, config_dict)
    trainer = Trainer(
        cfg=t,
        policy=policy,
        algorithm=algorithm,
        env=env,
        eval_env=eval_env,
        logger=logger,
        event_manager=EventManager(config.events.train, "events.train"),
        eval_event_manager=EventManager(config.events.eval, "events.eval"),
        run_dir=run_dir,
        config_dict=config_dict,
    )
    try:
        trainer.train(total)
        if eval_env is not None and not trainer.last_eval:
            trainer.eval_once()
    except KeyboardInterrupt:
        log.warning("interrupted at step %d: saving a checkpoint before exiting", trainer.global_step)
        trainer.save_checkpoint()
    finally:
        trainer.close()
    log.info("done: %d env steps; checkpoint %s", trainer.global_step, trainer.last_checkpoint)
    return trainer.last_eval


def _task(cfg: DictConfig) -> float | None:
    """Hydra's task function: typed config in, final eval return out (for sweepers)."""
    try:
        config = to_root_config(cfg)
    except ConfigError as exc:
        log.error("config error: %s", exc)
        sys.exit(2)
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        metrics: dict[str, Any] = train(config, run_dir)
    except ConfigError as exc:
        log.error("config error: %s", exc)
        sys.exit(2)
    return metrics.get("eval/episode_return")


def main() -> None:
    """``python train.py [overrides]``: compose ``conf/`` with Hydra and train."""
    register_configs()
    os.environ.setdefault("MUJOCO_GL", "egl")
    hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")(_task)()
