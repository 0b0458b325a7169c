"""A task's scene: its MJCF compiled with the config's ``env.native.scene`` overrides of its rigid
objects (``<uid>_init_pos``, ``_size``, ``_mass``, ``_friction``)."""

from __future__ import annotations

from importlib import resources
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np

from rlexp.config.native_task import Number, ParamRule, Vector
from rlexp.envs.native.registry import unknown_name_message

if TYPE_CHECKING:
    from rlexp.envs.native.tasks import TaskSpec


def _friction_ok(value: Any, where: str) -> None:
    values = value if isinstance(value, (list, tuple)) else [value]
    if not 1 <= len(values) <= 3:
        raise ValueError(
            f"{where}={value!r} must be 1 to 3 numbers >= 0 (sliding, torsional, rolling)"
        )
    for i, v in enumerate(values):
        Number(ge=0).check(v, f"{where}[{i}]" if isinstance(value, (list, tuple)) else where)


#: Rules of the scene overrides of a rigid object ``<uid>_<attr>`` (init_qpos: SimState._setup_indices).
SCENE_RULES: dict[str, ParamRule] = {
    "init_pos": Vector(note="m, world frame"),
    "size": Vector(gt=0, note="m, full edge lengths"),
    "mass": Number(gt=0, note=" (kg)"),
}


def load_model(task: TaskSpec, scene: dict[str, Any]) -> tuple[mujoco.MjModel, dict[str, Any]]:
    """Compile the task's MJCF with the ``scene`` overrides; returns the model and the unused ones."""
    path = resources.files("rlexp.envs.native") / "assets" / task.asset
    spec = mujoco.MjSpec.from_file(str(path))
    rest = {}
    for key, value in scene.items():
        uid, _, attr = key.partition("_")
        if key == "init_qpos":
            rest[key] = value
        elif uid in task.objects and attr in ("init_pos", "size", "mass", "friction"):
            if attr == "friction":
                _friction_ok(value, f"env.native.scene.{key}")
            else:
                SCENE_RULES[attr].check(value, f"env.native.scene.{key}")
            body = spec.body(task.objects[uid])
            geom = body.first_geom()
            if attr == "init_pos":
                body.pos = np.asarray(value, float)
            elif attr == "size":  # full edge lengths, as the task files give them
                geom.size = 0.5 * np.asarray(value, float)
            elif attr == "mass":
                geom.mass = float(value)
            else:
                fr = np.atleast_1d(np.asarray(value, float))
                geom.friction = np.concatenate([fr, geom.friction[len(fr) :]])
        else:
            choices = ["init_qpos"] + [
                f"{u}_{a}" for u in task.objects for a in ("init_pos", "size", "mass", "friction")
            ]
            raise KeyError(unknown_name_message("scene override", key, choices, "env.native.scene"))
    return spec.compile(), rest
