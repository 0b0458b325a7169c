"""Entry point: Hydra composes ``conf/``, ``train(config, run_dir)`` builds the objects and runs.

``main()`` is what ``python train.py`` and ``rlexp train`` call. Heavy libraries (torch, torchrl)
are imported only once the config has composed and validated, so a bad override fails in a second.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
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


def train(config: RootConfig, run_dir: Path, sweep_group: str | None = None) -> dict[str, float]:
    """Build envs, policy, PPO, loggers and Trainer from ``config``; train; return the last eval."""
    import torch

    from rlexp import _speedups
    from rlexp.algorithms.ppo import NonFiniteError, make_algorithm
    from rlexp.checkpoint import latest_good_checkpoint, load_checkpoint
    from rlexp.envs.factory import make_env
    from rlexp.events import EventManager
    from rlexp.launch import distributed
    from rlexp.launch.slurm import install_preemption_handler
    from rlexp.logging import MetricLogger, make_logger
    from rlexp.policies.actor_critic import make_policy
    from rlexp.provenance import versions, write_provenance
    from rlexp.trainer import StopRequested, Trainer

    t, e = config.trainer, config.env
    dist = distributed.info()
    _speedups.apply()
    torch.set_num_threads(t.torch_threads)
    device = resolve_device(t.device, t.strict_device)
    if dist.enabled and device.startswith("cuda"):
        device = f"cuda:{dist.local_rank}"  # each rank on its own GPU
    seed_everything(config.seed + dist.rank)
    run_dir.mkdir(parents=True, exist_ok=True)
    if t.resume == "auto" and (run_dir / "config.yaml").is_file():
        # Continuing in an existing run dir (requeue, re-run of a sweep dir): it must be the same
        # experiment, or results of two configs would be mixed in one run.
        saved = OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml"), resolve=True)
        diffs = config_differences(saved, to_dict(config), ignore=RESUME_MAY_CHANGE)
        if diffs:
            raise ConfigError(
                f"run dir {run_dir} holds a different experiment (differs in {', '.join(diffs)}); "
                "use a new hydra.run.dir / hydra.sweep.dir, or trainer.resume=never to start over there"
            )
    status = read_status(run_dir)
    if (
        status.get("state") == "finished"
        and t.resume == "auto"
        and status.get("global_step", 0) >= total_frames(config, dist.world_size)
    ):
        # A re-run of the same sweep: this job already finished its budget; report it, train nothing.
        log.info(
            "run dir %s already finished at step %s: skipping", run_dir, status.get("global_step")
        )
        return dict(status.get("final_eval") or {})

    t.device = device  # the saved config records the device actually used
    config_dict = to_dict(config)
    if dist.is_main:
        (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(config_dict)))
    from rlexp.config.json_format import write_json_experiment

    if dist.is_main:
        write_json_experiment(
            config, run_dir
        )  # the same config as train_config.json + gym_config.json
    if dist.is_main:
        write_provenance(run_dir, device)
    log.info("run dir: %s (device %s, seed %d)", run_dir, device, config.seed)

    # Resume before anything is built from scratch: a requeued job continues where it stopped.
    ckpt = None
    if t.resume == "auto":
        ckpt = latest_good_checkpoint(run_dir / "checkpoints")
    elif t.resume not in ("never", ""):
        ckpt = load_checkpoint(t.resume)
        diffs = config_differences(ckpt["config"], config_dict, ignore=RESUME_MAY_CHANGE)
        if diffs:
            log.warning("resuming %s with a different config (%s)", t.resume, ", ".join(diffs))

    env = make_env(e, e.num_envs, config.seed + dist.rank)  # each rank its own envs: seed + rank
    eval_env = None  # rank 0 alone evaluates
    if e.num_eval_envs > 0 and dist.is_main:
        eval_env = make_env(e, e.num_eval_envs, config.seed + 1_000_000)
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    log.info("env %s x%d: obs %d, action %d", e.name, e.num_envs, obs_dim, act_dim)
    policy = make_policy(
        config.policy,
        obs_dim,
        act_dim,
        env.action_spec,
        e.normalize_observations,
        e.clip_observations,
    ).to(device)
    if dist.enabled:  # same initial parameters everywhere
        distributed.broadcast_([*policy.parameters(), *policy.buffers()])
    total = total_frames(config, dist.world_size)
    iterations = -(-total // (t.frames_per_batch * dist.world_size))
    grad_sync = distributed.all_reduce_mean_ if dist.enabled else None
    algorithm = make_algorithm(config.algorithm, policy, iterations, t.nan_guard, grad_sync)
    if dist.is_main:
        logger = make_logger(config.logger, run_dir, t.exp_name, config_dict, group=sweep_group)
    else:
        logger = MetricLogger([])
    trainer = Trainer(
        cfg=t,
        policy=policy,
        algorithm=algorithm,
        env=env,
        eval_env=eval_env,
        logger=logger,
        event_manager=EventManager(config.events.train, "events.train", seed=config.seed + 2),
        eval_event_manager=EventManager(config.events.eval, "events.eval", seed=config.seed + 3),
        run_dir=run_dir,
        config_dict=config_dict,
        versions=versions(),
        dist=dist,
    )
    install_preemption_handler(
        trainer
    )  # under SLURM: the preemption signal checkpoints, then requeues
    if ckpt is not None:
        trainer.load_state_dict(ckpt)
    write_status(run_dir, "running", trainer.global_step)
    try:
        trainer.train(total)
        if eval_env is not None and not trainer.last_eval:
            trainer.eval_once()
        write_status(run_dir, "finished", trainer.global_step, trainer.last_eval)
    except KeyboardInterrupt:
        log.warning(
            "interrupted at step %d: saving a checkpoint before exiting", trainer.global_step
        )
        trainer.save_checkpoint()
        write_status(run_dir, "interrupted", trainer.global_step, trainer.last_eval)
    except StopRequested as exc:
        log.warning(
            "stopped at step %d (%s): checkpoint %s",
            trainer.global_step,
            exc,
            trainer.last_checkpoint,
        )
        write_status(run_dir, "stopped", trainer.global_step, trainer.last_eval, reason=str(exc))
        trainer.close()
        raise
    except NonFiniteError as exc:
        write_status(run_dir, "failed", trainer.global_step, trainer.last_eval, reason=str(exc))
        log.error(
            "stopped: %s; the last good checkpoint is %s",
            exc,
            trainer.last_checkpoint or ckpt and ckpt["path"],
        )
        trainer.close()
        sys.exit(3)
    finally:
        if not trainer.logger.closed:
            trainer.close()
        distributed.shutdown()
    log.info("done: %d env steps; checkpoint %s", trainer.global_step, trainer.last_checkpoint)
    return trainer.last_eval


#: Keys a continuation may change: the budget (train longer), how to resume, the device, the console.
RESUME_MAY_CHANGE = (
    "trainer.total_frames",
    "trainer.iterations",
    "trainer.resume",
    "trainer.device",
    "trainer.progress",
    "trainer.strict_device",
    "algorithm.compile",  # how the loss runs, not what it computes
)


def config_differences(
    a: dict[str, Any], b: dict[str, Any], ignore: tuple[str, ...] = (), prefix: str = ""
) -> list[str]:
    """Dotted keys whose values differ between two plain config dicts."""
    out = []
    for key in sorted(set(a) | set(b)):
        path = f"{prefix}{key}"
        if path in ignore:
            continue
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += config_differences(va, vb, ignore, path + ".")
        elif va != vb:
            out.append(path)
    return out


def read_status(run_dir: Path) -> dict[str, Any]:
    """``status.json`` of a run dir ({} when there is none)."""
    path = run_dir / "status.json"
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def write_status(
    run_dir: Path, state: str, global_step: int, final_eval: dict | None = None, **extra: Any
) -> None:
    """``status.json``: running | finished | interrupted | stopped | failed, the step and the last eval
    (what sweeps and ``rlexp report`` read to tell finished jobs from unfinished ones). Rank 0 only."""
    from rlexp.launch.distributed import info

    if not info().is_main:
        return
    info = {
        "state": state,
        "global_step": global_step,
        "final_eval": final_eval or {},
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        **extra,
    }
    tmp = run_dir / ".status.json.tmp"
    tmp.write_text(json.dumps(info, indent=2) + "\n")
    os.replace(tmp, run_dir / "status.json")


def _task(cfg: DictConfig) -> float | None:
    """Hydra's task function: typed config in, final eval return out (for sweepers)."""
    try:
        config = to_root_config(cfg)
    except ConfigError as exc:
        log.error("config error: %s", exc)
        sys.exit(2)
    if os.environ.get("RLEXP_DISTRIBUTED") == "1":
        from rlexp.launch import distributed

        if not distributed.info().enabled:
            try:
                distributed.init_in_job()
            except RuntimeError as exc:
                log.error("%s", exc)
                sys.exit(2)
    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    sweep_group = (
        Path(hc.sweep.dir).name if hc.mode is not None and hc.mode.name == "MULTIRUN" else None
    )
    try:
        metrics: dict[str, Any] = train(config, run_dir, sweep_group)
    except ConfigError as exc:
        log.error("config error: %s", exc)
        sys.exit(2)
    return metrics.get("eval/episode_return")


def main() -> None:
    """``python train.py [--distributed] [overrides]``: compose ``conf/`` with Hydra and train."""
    from rlexp.launch import distributed

    register_configs()
    os.environ.setdefault("MUJOCO_GL", "egl")
    wanted, rest = distributed.split_flag(sys.argv[1:])
    if wanted and any(a in ("-m", "--multirun") for a in rest):
        # A sweep: the launcher's jobs start the ranks (SLURM tasks_per_node); each job joins its group.
        os.environ["RLEXP_DISTRIBUTED"] = "1"
        sys.argv = [sys.argv[0], *rest]
    elif wanted:
        try:
            rest = distributed.init(rest)
        except RuntimeError as exc:
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(2)
        sys.argv = [sys.argv[0], *rest]
    hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")(_task)()
