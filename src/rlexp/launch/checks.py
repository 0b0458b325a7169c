"""Checks that need the libraries: build the env, policy and event managers once, and read the
checkpoint given to ``trainer.resume``, so that a config that cannot run fails before anything is
written (``python train.py``: before Hydra creates the run dir; in a sweep: before the job writes).
"""

from __future__ import annotations

import dataclasses
import logging
import re
from typing import Any

from rlexp.config.rules import first_line
from rlexp.config.schema import RootConfig
from rlexp.config.validate import ConfigError

log = logging.getLogger(__name__)


def check_buildable(config: RootConfig) -> None:
    """Build one env copy, the policy and the event managers; check a resume checkpoint against them.
    User code that exits or raises ``KeyboardInterrupt`` (at its import, in its env's constructor,
    reset or step) is a config error like any other it raises (``rlexp.runtime.user_code``)."""
    from rlexp.runtime.user_code import UserCodeExit, user_code_exits

    try:
        with user_code_exits(f"env.name={config.env.name!r} while the config was checked"):
            _check_buildable(config)
    except UserCodeExit as exc:
        raise ConfigError(str(exc)) from None


def _check_buildable(config: RootConfig) -> None:
    from rlexp.envs.factory import make_env
    from rlexp.events import EventManager
    from rlexp.extras import check_config
    from rlexp.policies.actor_critic import policy_for_env

    check_config(config)  # an optional part it turns on is installed (W&B, mp4 videos)
    from rlexp.training.build import resolve_device

    if config.trainer.strict_device:  # CUDA asked for and required: it must be there
        resolve_device(config.trainer.device, strict=True)
    e = config.env
    try:
        env = make_env(e, 1, config.seed)
    except ConfigError:
        raise
    except Exception as exc:
        msg = first_line(exc)
        if "box2d" in msg.lower():  # Gymnasium's own hint names swig; rlexp's extra has wheels
            from rlexp.extras import require

            require("box2d", f"env.name={e.name!r}")
        bad = _refused_kwarg(e.name, e.kwargs, msg)
        if bad is not None and not msg.startswith("env."):
            from rlexp.envs.gym_ids import kwarg_hint, render_refusal

            refusal = (
                render_refusal(e.name, "env.kwargs.render_mode") if bad == "render_mode" else None
            )
            msg = refusal or (
                f"env.kwargs.{bad} is not an argument of {e.name} "
                f"(gymnasium.make({e.name!r}, ...) refused it){kwarg_hint(e.name, bad)}"
            )
        elif not msg.startswith("env."):
            msg = f"env.name={e.name!r} (env.backend={e.backend}) cannot be built: {msg}"
        raise ConfigError(msg) from None
    t = config.trainer
    try:
        if hasattr(env, "check_first_step"):  # a batched torch env: its first step, checked
            env.check_first_step()
        _check_env_state(env, e.name)
        # (built to check, never trained: the orthogonal init, ~0.1 s of QR for a CNN, left out)
        policy = policy_for_env(_without_init(config.policy), e, env)
        train_events = EventManager(config.events.train, "events.train")
        eval_events = EventManager(config.events.eval, "events.eval")
        # Each event checks itself on the env (record_video renders one frame at its resolution).
        train_events.check_env(env, num_envs=e.num_envs)
        if e.num_eval_envs > 0 and t.eval_every > 0 and t.eval_episodes > 0:
            eval_events.check_env(env, num_envs=e.num_eval_envs)
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(first_line(exc)) from None
    finally:
        env.close()
    if config.trainer.resume not in ("auto", "never", ""):
        check_resume_checkpoint(config, policy)


def _without_init(policy_cfg: Any) -> Any:
    """The policy config with ``ortho_init`` off, where it has one (the check builds the policy
    only for its shapes and refusals)."""
    if getattr(policy_cfg, "ortho_init", False) and dataclasses.is_dataclass(policy_cfg):
        return dataclasses.replace(policy_cfg, ortho_init=False)
    return policy_cfg


def _refused_kwarg(name: str, kwargs: dict, msg: str) -> str | None:
    """The ``env.kwargs`` key a Gymnasium env's constructor refused: the one its TypeError names
    (``unexpected keyword argument 'x'``), or (``takes no arguments``) the first its signature
    lacks; None when the failure is something else."""
    named = re.search(r"unexpected keyword argument '([^']+)'", msg)
    if named:
        return named.group(1) if named.group(1) in kwargs else None
    if "takes no arguments" not in msg and "positional argument" not in msg:
        return None
    from rlexp.envs.gym_ids import MAKE_KWARGS, constructor_args

    args = constructor_args(name)
    unknown = [k for k in kwargs if args is not None and k not in (*args, *MAKE_KWARGS)]
    return unknown[0] if unknown else None


def _check_env_state(env: Any, name: str) -> None:
    """What a checkpoint will hold of the env: an env's ``get_state()`` that fails or returns
    something a checkpoint cannot hold is one line now, not a surprise at the first checkpoint."""
    if getattr(env, "state_kind", None) != "state":  # only an env's own get_state() can fail
        return
    env.reset()
    try:
        env.env_state(strict=True)
    except Exception as exc:
        if first_line(exc).startswith("env.name="):
            raise TypeError(first_line(exc)) from None
        raise TypeError(
            f"env.name={name!r}: get_state() failed ({type(exc).__name__}: {first_line(exc)}); "
            "docs/envs.md, 'The state protocol'"
        ) from None


def check_resume_checkpoint(config: RootConfig, policy: Any) -> dict[str, Any]:
    """Load ``trainer.resume`` and check it fits this run: an rlexp checkpoint of the same env whose
    policy loads into this policy; returns it."""
    from pathlib import Path

    from rlexp.algorithms.replay_files import locate_chunks
    from rlexp.checkpoints.files import check_checkpoint_fits, load_checkpoint

    where = f"trainer.resume={config.trainer.resume!r}"
    try:
        ckpt = load_checkpoint(config.trainer.resume, "resume")
        locate_chunks(ckpt, Path(ckpt["path"]))  # SAC / TD3: its replay rows, in its run dir
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{where}: {first_line(exc)}") from None
    try:
        check_checkpoint_fits(ckpt, config, policy)
    except ValueError as exc:
        raise ConfigError(f"{where}: {first_line(exc)}") from None
    return ckpt
