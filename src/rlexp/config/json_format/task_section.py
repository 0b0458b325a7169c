"""The task file: its ``id`` mapped to a conf/env group and native task, the time limit, the term
sections (added to the env YAML's) and the scene, as ``env.*`` leaves."""

from __future__ import annotations

import difflib
import re
from pathlib import Path
from typing import Any

from rlexp.config.json_format.leaves import _Mapped, flatten
from rlexp.config.json_format.typed_reads import _File, _show

#: Task ids of the format -> our native task (conf/env/<name>.yaml). Gymnasium ids of the env YAMLs
#: (e.g. HalfCheetah-v5) are accepted too, so that every rlexp run can be written in this format.
TASK_IDS = {"PushCubeRL": "push_cube", "CartPoleRL": "cart_pole"}
GYM_KEYS = (
    "id", "max_episodes", "max_episode_steps", "num_envs", "env", "robot", "sensor", "light", "background",
    "rigid_object", "rigid_object_group", "articulation",
)  # fmt: skip
GYM_ENV_KEYS = ("events", "observations", "rewards", "actions", "extensions", "num_envs")
#: Term kind -> (keys a term may have, defaults filled in, modes).
TERM_KEYS: dict[str, tuple[tuple[str, ...], dict[str, Any], tuple[str, ...]]] = {
    "events": (
        ("func", "mode", "interval_step", "params"),
        {"mode": "reset", "interval_step": 1},
        ("startup", "reset", "interval"),
    ),
    "observations": (("func", "mode", "name", "params"), {"mode": "add"}, ("add", "modify")),
    "rewards": (
        ("func", "mode", "weight", "params"),
        {"mode": "add", "weight": 1.0},
        ("add", "replace"),
    ),
    "actions": (("func", "params"), {}, ()),
}


# --------------------------------------------------------------------------- registries (lazy)


def _native() -> Any:
    """``rlexp.envs.native`` (imported when first needed: it imports MuJoCo)."""
    import rlexp.envs.native as native

    return native


def _term_registry(kind: str) -> list[str]:
    """Registered names of one kind of task term."""
    reg = {
        "events": "EVENTS",
        "observations": "OBSERVATIONS",
        "rewards": "REWARDS",
        "actions": "ACTIONS",
    }[kind]
    return list(getattr(_native(), reg))


def _task_spec(task: str) -> tuple[tuple[str, ...], int | None]:
    """(scene object uids, number of robot joints) of a native task."""
    spec = _native().get_task(task)
    return tuple(spec.objects), len(spec.robot_joints)


# ------------------------------------------------------------------------------------ env groups


def _conf_dir() -> Path:
    from rlexp.config.paths import CONF_DIR

    return CONF_DIR


def _env_yaml(group: str) -> dict[str, Any] | None:
    """conf/env/<group>.yaml as a plain dict (without its defaults list), or None."""
    from omegaconf import OmegaConf

    path = _conf_dir() / "env" / f"{group}.yaml"
    if not path.is_file():
        return None
    node = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    node.pop("defaults", None)
    return node


def _gym_ids() -> dict[str, str]:
    """Gymnasium ids of the env YAMLs -> their group (HalfCheetah-v5 -> half_cheetah)."""
    out = {}
    for path in sorted((_conf_dir() / "env").glob("*.yaml")):
        node = _env_yaml(path.stem) or {}
        if node.get("backend", "gymnasium") != "native" and isinstance(node.get("name"), str):
            out[node["name"]] = path.stem
    return out


def _task_of(gf: _File, task_id: str, rlexp_env: dict[str, Any]) -> tuple[str, str | None]:
    """(env group, native task or None) of a task file's ``id``."""
    if task_id in TASK_IDS:
        return TASK_IDS[task_id], TASK_IDS[task_id]
    gym_ids = _gym_ids()
    if task_id in gym_ids:
        return gym_ids[task_id], None
    if rlexp_env.get("env.backend", "native") != "native":
        return "", None  # a Gymnasium id no env YAML has: the rlexp section says how to build it
    choices = [*TASK_IDS, *gym_ids]
    close = difflib.get_close_matches(task_id, choices, n=1)
    raise gf.error(
        f"id={task_id!r} is not a known task; choose from {choices}"
        + (f"; did you mean {close[0]!r}?" if close else "")
    )


def _map_task(
    gf: _File, g: dict[str, Any], genv: dict[str, Any], rlexp_env: dict[str, Any], m: _Mapped
) -> None:
    """The task file: env group, time limit, term sections (added to the YAML's), scene."""
    from rlexp.config.schema import EnvConfig

    out = m.leaves
    task_id = gf.get(g, "id", "", "str")
    group, task = _task_of(gf, task_id, rlexp_env)
    yaml_node = _env_yaml(group) if group else None
    base = yaml_node if yaml_node is not None else {}
    if task is not None:
        base.setdefault("name", task)
        base.setdefault("backend", "native")
        base.setdefault("native", {}).setdefault("task", task)
        out["env.backend"] = "native"
        out["env.native.task"] = task
    else:
        out["env.name"] = task_id
    m.env_group = group
    m.env_base = {f"env.{k}": v for k, v in flatten(base, EnvConfig).items()}
    out["env.max_episode_steps"] = gf.get(g, "max_episode_steps", "", "int", 300, low=1)
    if "max_episodes" in g:
        gf.get(g, "max_episodes", "", "int", low=0)
        m.not_applicable.append("max_episodes")

    terms = {
        kind: _terms(gf, gf.get(genv, kind, "env", "object", {}), kind, task is not None)
        for kind in ("events", "observations", "rewards", "actions")
    }
    extensions = gf.get(genv, "extensions", "env", "object", {})
    if task is None:
        if any(terms.values()) or extensions:
            raise gf.error(
                f"env terms apply to the native tasks {list(TASK_IDS)} only, not to {task_id!r}; "
                "leave env empty"
            )
        scene_keys = ("robot", "sensor", "light", "background", "rigid_object")
        m.not_applicable += [
            k for k in (*scene_keys, "rigid_object_group", "articulation") if g.get(k)
        ]
        return
    # The task's own terms (conf/env/<task>.yaml: e.g. CartPole's upright reward, which the task
    # defines and the users' file only adds a penalty to) stay; the file's terms are added, and
    # replace a YAML term of the same name.
    yaml_terms = (yaml_node or {}).get("native", {}) if yaml_node is not None else {}
    for kind, value in terms.items():
        out[f"env.native.{kind}"] = value
        m.yaml_parts[f"env.native.{kind}"] = dict(yaml_terms.get(kind) or {})
    out["env.native.extensions"] = extensions
    out["env.native.scene"] = _scene(gf, g, task, m.not_applicable)
    m.yaml_parts["env.native.scene"] = dict(m.env_base.get("env.native.scene") or {})
    if yaml_node is not None:
        kept = [
            f"{kind}.{name}"
            for kind in terms
            for name in (yaml_terms.get(kind) or {})
            if name not in terms[kind]
        ]
        if kept:
            m.notes.append(
                f"task terms of conf/env/{group}.yaml kept beside the file's: " + ", ".join(kept)
            )


def _terms(gf: _File, terms: dict[str, Any], kind: str, native: bool) -> dict[str, Any]:
    """One kind of task term (env.events / observations / rewards / actions) as schema dicts."""
    keys, defaults, modes = TERM_KEYS[kind]
    names = _term_registry(kind) if native else None
    out = {}
    for name, term in terms.items():
        w = f"env.{kind}.{name}"
        term = gf.obj(term, w, keys)
        func = gf.get(term, "func", w, "str")
        if names is not None and func not in names:
            close = difflib.get_close_matches(func, names, n=1)
            raise gf.error(
                f"{w}.func={func!r} is not a known {kind[:-1]} term; choose from {sorted(names)}"
                + (f"; did you mean {close[0]!r}?" if close else "")
            )
        entry: dict[str, Any] = {"func": func}
        if "mode" in keys:
            entry["mode"] = gf.get(term, "mode", w, "str", defaults["mode"], choices=modes)
        if kind == "events":
            entry["interval_step"] = gf.get(term, "interval_step", w, "int", 1, low=1)
        if kind == "observations":
            obs_name = gf.get(term, "name", w, "str")
            if not re.fullmatch(r"[^/]+/[^/]+", obs_name):
                raise gf.error(f"{w}.name={obs_name!r} must be 'group/key' (e.g. 'robot/qpos')")
            entry["name"] = obs_name
        if kind == "rewards":
            entry["weight"] = gf.get(term, "weight", w, "number", 1.0)
        entry["params"] = gf.get(term, "params", w, "object", {})
        out[name] = entry
    return out


def _scene(gf: _File, g: dict[str, Any], task: str, na: list[str]) -> dict[str, Any]:
    """The parts of robot / rigid_object that shape the rebuild, as env.native.scene overrides:
    ``init_qpos``, ``<uid>_init_pos``, ``<uid>_size``, ``<uid>_mass``, ``<uid>_friction``."""
    objects, num_joints = _task_spec(task)
    scene: dict[str, Any] = {}
    robot = gf.obj(gf.get(g, "robot", "", "object", {}), "robot")
    for key in sorted(robot):
        if key == "init_qpos":
            qpos = gf.get(robot, "init_qpos", "robot", "numbers")
            if num_joints is not None and len(qpos) < num_joints:
                raise gf.error(
                    f"robot.init_qpos has {len(qpos)} values; the {task} rebuild has {num_joints} robot joints"
                )
            if num_joints is not None and len(qpos) > num_joints:
                na.append(
                    f"robot.init_qpos[{num_joints}:] (joints the {task} rebuild does not have)"
                )
                qpos = qpos[:num_joints]
            scene["init_qpos"] = qpos
        elif key != "uid" and robot[key] not in ({}, [], None, ""):
            na.append(f"robot.{key}")
    for key in ("sensor", "background", "rigid_object_group", "articulation"):
        if gf.get(g, key, "", "list", []):
            na.append(key)
    if gf.get(g, "light", "", "object", {}):
        na.append("light")
    for i, obj in enumerate(gf.get(g, "rigid_object", "", "list", [])):
        w = f"rigid_object[{i}]"
        obj = gf.obj(obj, w)
        uid = gf.get(obj, "uid", w, "str")
        if uid not in objects:
            na.append(f"{w} (uid {uid!r}: the {task} rebuild has objects {list(objects)})")
            continue
        for key in sorted(obj):
            if key == "init_pos":
                pos = gf.get(obj, "init_pos", w, "numbers")
                if len(pos) != 3:
                    raise gf.error(f"{w}.init_pos={_show(pos)} must have 3 values")
                scene[f"{uid}_init_pos"] = pos
            elif key == "shape":
                shape = gf.obj(obj["shape"], f"{w}.shape")
                stype = gf.get(shape, "shape_type", f"{w}.shape", "str", "Cube")
                if stype != "Cube":
                    raise gf.error(
                        f"{w}.shape.shape_type={stype!r}: the {task} rebuild's {uid} is a Cube"
                    )
                if "size" in shape:
                    size = gf.get(shape, "size", f"{w}.shape", "numbers", positive=True)
                    if len(size) != 3:
                        raise gf.error(f"{w}.shape.size={_show(size)} must have 3 values")
                    scene[f"{uid}_size"] = size
                na.extend(f"{w}.shape.{k}" for k in shape if k not in ("shape_type", "size"))
            elif key == "attrs":
                attrs = gf.obj(obj["attrs"], f"{w}.attrs")
                if "mass" in attrs:
                    scene[f"{uid}_mass"] = gf.get(
                        attrs, "mass", f"{w}.attrs", "number", positive=True
                    )
                # MuJoCo has one Coulomb coefficient: the sliding (dynamic) one, as a pushed cube slides
                for k in ("dynamic_friction", "static_friction"):
                    if k in attrs:
                        scene[f"{uid}_friction"] = [
                            gf.get(attrs, k, f"{w}.attrs", "number", low=0.0)
                        ]
                        break
                if "dynamic_friction" in attrs and "static_friction" in attrs:
                    gf.get(attrs, "static_friction", f"{w}.attrs", "number", low=0.0)
                    na.append(
                        f"{w}.attrs.static_friction (MuJoCo has one coefficient: dynamic_friction is used)"
                    )
                na.extend(
                    f"{w}.attrs.{k}"
                    for k in attrs
                    if k not in ("mass", "static_friction", "dynamic_friction")
                )
            elif key == "body_type":
                if gf.get(obj, "body_type", w, "str") != "dynamic":
                    na.append(f"{w}.body_type")
            elif key != "uid":
                na.append(f"{w}.{key}")
    return scene
