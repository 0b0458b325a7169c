"""The run's objects, built from the typed config in order: envs, policy, algorithm, event managers,
and then the Trainer. Building writes nothing; the Trainer is made once the run dir may be written."""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rlexp.config.schema import RootConfig

log = logging.getLogger(__name__)


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (the envs are seeded where they are built)."""
    import random

    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def resolve_device(device: str, strict: bool = False) -> str:
    """``auto`` -> ``cuda`` when a GPU is visible, else ``cpu``; CUDA asked on a CPU-only machine
    falls back to CPU with one warning unless ``strict`` (``rlexp.runtime.devices``). The training run
    decides ``auto`` from its built env instead (``build``)."""
    from rlexp.runtime.devices import resolve_device as resolve

    return resolve(device, strict)


def training_device(requested: str, env: Any, config: RootConfig) -> str:
    """``trainer.device`` for this run: as given (resolved by the app), or ``auto`` decided from
    the env just built (``rlexp.runtime.devices.auto_device``), logged once with why."""
    if requested != "auto":
        return requested
    from rlexp.runtime import distributed
    from rlexp.runtime.devices import auto_device

    dist = distributed.info()
    local_rank = dist.local_rank if dist.enabled else None
    device, why = auto_device(getattr(env, "device", None), config.policy, local_rank)
    log.info("[device] trainer.device=auto -> %s: %s", device, why)
    return device


#: The eval envs' seed is the run's seed plus this (far from the per-rank training seeds).
EVAL_SEED_OFFSET = 1_000_000


@dataclass
class Built:
    """The run's objects before the Trainer exists (building them writes nothing)."""

    config: RootConfig
    run_dir: Path
    env: Any
    eval_env: Any
    policy: Any
    algorithm: Any
    events: Any
    eval_events: Any
    device: str = "cpu"  # trainer.device as used (auto decided from the env)

    def trainer(
        self, logger: Any, config_dict: dict, versions: dict, eval_async: bool = False
    ) -> Any:
        """The Trainer; ``eval_async`` (``trainer.eval_async`` resolved by the app): its eval rounds
        run in a worker process beside training (rank 0, where an eval env exists)."""
        from rlexp.hooks import HookManager
        from rlexp.pbt.exploit import load_training_state
        from rlexp.runtime import distributed
        from rlexp.training.eval_worker import EvalSetup, EvalWorker
        from rlexp.training.trainer import Trainer

        c = self.config
        worker = None
        if eval_async and self.eval_env is not None:
            device = str(next(self.policy.parameters()).device)
            setup = EvalSetup(
                c.env,
                c.policy,
                c.seed + EVAL_SEED_OFFSET,
                c.trainer.eval_episodes,
                device,
                c.trainer.precision,
            )
            worker = EvalWorker(setup, timeout_s=c.trainer.stall_timeout_s)  # a stuck one fails
        return Trainer(
            cfg=self.config.trainer,
            policy=self.policy,
            algorithm=self.algorithm,
            env=self.env,
            eval_env=self.eval_env,
            logger=logger,
            event_manager=self.events,
            eval_event_manager=self.eval_events,
            run_dir=self.run_dir,
            config_dict=config_dict,
            versions=versions,
            dist=distributed.info(),
            eval_seed=self.config.seed + EVAL_SEED_OFFSET,
            console=self.config.logger.console,
            hooks=HookManager(
                self.config.hooks,
                self.algorithm.hyperparameters(),
                loader=functools.partial(load_training_state, self.policy),  # PBT's exploit
            ),
            eval_worker=worker,
            overlap=getattr(c.algorithm, "overlap", False),
        )


def build(config: RootConfig, run_dir: Path, device: str, total: int) -> Built:
    """Envs, policy, algorithm and event managers, in that order (nothing is written); ``device``:
    the policy's, or ``auto`` (decided once the training env exists: ``training_device``)."""
    from rlexp.algorithms import make_algorithm
    from rlexp.envs.factory import make_env
    from rlexp.events import EventManager
    from rlexp.policies.actor_critic import policy_for_env
    from rlexp.runtime import distributed
    from rlexp.runtime.precision import set_precision, warn_if_slow

    t, e = config.trainer, config.env
    dist = distributed.info()
    env = make_env(e, e.num_envs, config.seed + dist.rank)  # each rank its own envs: seed + rank
    eval_env = None  # rank 0 alone evaluates; eval_every=0 or eval_episodes=0: no evaluation at all
    if e.num_eval_envs > 0 and dist.is_main and t.eval_every > 0 and t.eval_episodes > 0:
        eval_env = make_env(e, e.num_eval_envs, config.seed + EVAL_SEED_OFFSET)
    elif config.events.eval and dist.is_main:
        log.warning(
            "events.eval (%s) never fire: evaluation is off (trainer.eval_every=%d, "
            "trainer.eval_episodes=%d, env.num_eval_envs=%d; a JSON file's enable_eval: false)",
            ", ".join(config.events.eval),
            t.eval_every,
            t.eval_episodes,
            e.num_eval_envs,
        )
    if hasattr(env, "warn_action_bounds"):  # a Box not in [-1, 1]: once, in the run's log
        env.warn_action_bounds()
    log.info(
        "env %s x%d: obs %s, action %d%s",
        e.name,
        e.num_envs,
        observation_summary(env.observation_spec["observation"]),
        env.action_spec.shape[-1],
        env_section_note(e),
    )
    device = training_device(device, env, config)
    if getattr(config.algorithm, "overlap", False) and (dist.enabled or device != "cpu"):
        from rlexp.config.validate import ConfigError

        raise ConfigError(
            "algorithm.overlap=true forks a collection process beside one training process on "
            f"the CPU (here: {'--distributed, ' if dist.enabled else ''}device {device!r}); set "
            "algorithm.overlap=false" + ("" if device == "cpu" else " or trainer.device=cpu")
        )
    policy = policy_for_env(config.policy, e, env).to(device)
    # trainer.precision: before the learner, which makes its Q networks and fused steps from it
    set_precision(policy, t.precision, device)
    warn_if_slow(t.precision, device)
    if dist.enabled:  # same initial parameters everywhere
        distributed.broadcast_([*policy.parameters(), *policy.buffers()])
    iterations = -(-total // (t.frames_per_batch * dist.world_size))
    grad_sync = distributed.all_reduce_mean_ if dist.enabled else None
    algorithm = make_algorithm(
        config.algorithm,
        policy,
        iterations,
        t.nan_guard,
        grad_sync,
        run_dir,
        config.seed + dist.rank,
    )
    return Built(
        config=config,
        run_dir=run_dir,
        env=env,
        eval_env=eval_env,
        policy=policy,
        algorithm=algorithm,
        events=EventManager(config.events.train, "events.train", seed=config.seed + 2),
        eval_events=EventManager(config.events.eval, "events.eval", seed=config.seed + 3),
        device=device,
    )


def observation_summary(spec: Any) -> str:
    """``17``, or (a TensorDict observation) ``vector 4 + pixels uint8 [3, 84, 84]``."""
    if not hasattr(spec, "keys"):
        return str(int(spec.shape[-1]))
    dims = len(spec.shape)
    return " + ".join(
        f"{k} {int(v.shape[-1])}" if v.dtype.is_floating_point else
        f"{k} {str(v.dtype).replace('torch.', '')} {list(v.shape[dims:])}"
        for k, v in spec.items()
    )  # fmt: skip


def env_section_note(e: Any) -> str:
    """Where the env's other settings came from, when ``env.name`` was given on the command line
    with an env option made for another task (``env.name=mymod:MyEnv-v0`` alone keeps the default
    ``env=half_cheetah``'s copies, evaluation and normalisation): that option and ``env=gym``."""
    from rlexp.run.rundir import HYDRA_JOB

    hydra = HYDRA_JOB.get("hydra")
    if hydra is None:
        return ""  # not under Hydra (train() called from Python)
    choice = hydra.runtime.choices.get("env")
    named = any(str(o).lstrip("+~").startswith("env.name=") for o in hydra.overrides.task)
    if choice in (None, "gym") or not named:
        return ""
    return (
        f" (its other settings are env={choice}'s: num_envs={e.num_envs}, num_eval_envs="
        f"{e.num_eval_envs}, normalize_observations={str(e.normalize_observations).lower()}, "
        f"max_episode_steps={e.max_episode_steps}; env=gym env.name={e.name} has defaults for any "
        "Gymnasium id)"
    )
