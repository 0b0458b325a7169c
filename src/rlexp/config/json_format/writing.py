"""Writing a config back out in the format: ``to_json_experiment`` (the format's keys plus an
``rlexp`` section with everything else, so that the pair loads back to the same config),
``dumps`` (laid out as the users' files) and ``write_json_experiment`` (into a run dir)."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import typing
from pathlib import Path
from typing import Any

from rlexp.config.json_format.convert import _convert
from rlexp.config.json_format.leaves import flatten, nest
from rlexp.config.json_format.task_section import TASK_IDS
from rlexp.config.json_format.train_section import ALGORITHM_FORMAT_KEYS
from rlexp.config.json_format.trainer_events import EVENT_ALIASES
from rlexp.config.json_format.typed_reads import _File
from rlexp.config.validate import ConfigError

if typing.TYPE_CHECKING:
    from rlexp.config.schema import RootConfig

log = logging.getLogger(__name__)


def _plain(config: RootConfig) -> dict[str, Any]:
    """``config`` as plain dicts, strings as they are: not through OmegaConf, which would read a
    ``"${...}"`` in a value (data, from a file) as an interpolation and resolve it."""
    return dataclasses.asdict(config)


def _task_id(env: Any) -> str:
    if env.backend == "native" and env.native is not None:
        for task_id, task in TASK_IDS.items():
            if task == env.native.task:
                return task_id
        return env.native.task
    return env.name


def _format_dicts(config: RootConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """The format's keys for ``config`` (no ``rlexp`` section)."""
    t, e, p, a, lg = config.trainer, config.env, config.policy, config.algorithm, config.logger
    d = _plain(config)
    trainer: dict[str, Any] = {
        "exp_name": t.exp_name,
        "gym_config": "gym_config.json",
        "seed": config.seed,
        "device": t.device,
        "num_envs": e.num_envs,
        "iterations": t.iterations
        if t.iterations is not None
        else max(1, -(-t.total_frames // t.frames_per_batch)),
        "buffer_size": t.frames_per_batch // e.num_envs,
        "enable_eval": e.num_eval_envs > 0,
    }
    if e.num_eval_envs > 0:
        trainer["num_eval_envs"] = e.num_eval_envs
        trainer["num_eval_episodes"] = max(1, -(-t.eval_episodes // e.num_eval_envs))
        trainer["eval_freq"] = t.eval_every
    trainer["save_freq"] = t.save_every
    trainer["use_wandb"] = lg.wandb.enabled
    trainer["wandb_project_name"] = lg.wandb.project
    reverse = {v: k for k, v in EVENT_ALIASES.items()}
    trainer["events"] = {
        phase: {
            name: {**ev, "func": reverse.get(ev["func"], ev["func"])}
            for name, ev in d["events"][phase].items()
        }
        for phase in ("train", "eval")
    }
    policy = {"name": p.name}
    for part in ("actor", "critic"):
        net = getattr(p, part, None)
        if net is None:  # actor_only: no critic
            continue
        policy[part] = {
            "type": "mlp",
            "network_cfg": {"hidden_sizes": list(net.hidden_sizes), "activation": net.activation},
        }
    algorithm = {
        "name": a.name,
        "cfg": {
            key: getattr(a, target)
            for key, (target, _) in ALGORITHM_FORMAT_KEYS[a.name].items()
            if target is not None
        },
    }
    train = {"trainer": trainer, "policy": policy, "algorithm": algorithm}

    gym: dict[str, Any] = {"id": _task_id(e)}
    if e.max_episode_steps is not None:
        gym["max_episode_steps"] = e.max_episode_steps
    gym["num_envs"] = e.num_envs
    if e.backend == "native" and e.native is not None:
        nd = d["env"]["native"]
        gym["env"] = {
            k: nd[k] for k in ("events", "observations", "rewards", "actions", "extensions")
        }
        # the format has no observation group (its "group/key" names nest the dict): a term's
        # group goes to the rlexp section (to_json_experiment), the term here without it
        gym["env"]["observations"] = {
            k: {f: v for f, v in t.items() if f != "group"}
            for k, t in (nd["observations"] or {}).items()
        }
        scene = dict(nd.get("scene") or {})
        if "init_qpos" in scene:
            gym["robot"] = {"init_qpos": scene["init_qpos"]}
        uids = sorted(
            {
                k.rsplit("_", 1)[0]
                for k in scene
                if k != "init_qpos" and k.endswith(("_size", "_mass", "_friction"))
            }
            | {k[: -len("_init_pos")] for k in scene if k.endswith("_init_pos")}
        )
        objects = []
        for uid in uids:
            obj: dict[str, Any] = {"uid": uid}
            if f"{uid}_size" in scene:
                obj["shape"] = {"shape_type": "Cube", "size": scene[f"{uid}_size"]}
            obj["body_type"] = "dynamic"
            if f"{uid}_init_pos" in scene:
                obj["init_pos"] = scene[f"{uid}_init_pos"]
            attrs = {}
            if f"{uid}_mass" in scene:
                attrs["mass"] = scene[f"{uid}_mass"]
            friction = scene.get(f"{uid}_friction")
            if isinstance(friction, list) and len(friction) == 1:
                attrs["dynamic_friction"] = friction[0]
            if attrs:
                obj["attrs"] = attrs
            objects.append(obj)
        if objects:
            gym["rigid_object"] = objects
    return train, gym


def to_json_experiment(config: RootConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """(train file, task file) dicts in the format that load back to exactly ``config``: the format's
    keys, plus an ``rlexp`` section with every other config key (and any the format rounds)."""
    from rlexp.config.schema import RootConfig

    if config.algorithm.name not in ALGORITHM_FORMAT_KEYS:  # the users' format names ppo / grpo
        raise ConfigError(
            f"algorithm={config.algorithm.name}: the JSON format has PPO and GRPO only (config.yaml "
            "holds this run's config)"
        )
    train, gym = _format_dicts(config)
    env_backend = {"env.backend": config.env.backend}
    mapped = _convert(
        json.loads(json.dumps(train)),
        json.loads(json.dumps(gym)),
        _File("train_config.json"),
        _File("gym_config.json"),
        env_backend,
    )
    leaves = flatten(_plain(config), RootConfig)
    extra = {
        k: v for k, v in leaves.items() if k not in mapped.leaves or not _same(mapped.leaves[k], v)
    }
    if extra:
        train["rlexp"] = nest(extra)
    return train, gym


def _same(a: Any, b: Any) -> bool:
    """Equal as JSON values (1 == 1.0, but True != 1)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) or isinstance(b, float):
        return (
            isinstance(a, (int, float))
            and isinstance(b, (int, float))
            and (a == b or (math.isnan(a) and math.isnan(b)))
        )
    return a == b


def dumps(value: Any, indent: int = 0) -> str:
    """JSON with objects one key a line and lists of plain values on one line (as the users' files)."""
    pad, inner = "  " * indent, "  " * (indent + 1)
    if isinstance(value, dict) and value:
        items = [f"{inner}{json.dumps(str(k))}: {dumps(v, indent + 1)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + f"\n{pad}}}"
    if isinstance(value, list) and any(isinstance(v, (dict, list)) for v in value):
        return "[\n" + ",\n".join(f"{inner}{dumps(v, indent + 1)}" for v in value) + f"\n{pad}]"
    return json.dumps(value)


def write_json_experiment(config: RootConfig, run_dir: Path) -> None:
    """Write ``train_config.json`` + ``gym_config.json`` (the resolved config in the users' format)
    into ``run_dir``; a config the format cannot express is logged, not fatal."""
    try:
        train, gym = to_json_experiment(config)
    except ConfigError as exc:
        log.warning("config not written as JSON (train_config.json): %s", exc)
        return
    (Path(run_dir) / "train_config.json").write_text(dumps(train) + "\n")
    (Path(run_dir) / "gym_config.json").write_text(dumps(gym) + "\n")
