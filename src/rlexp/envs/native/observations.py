"""Observation terms: ``func(env, **params) -> [N, ...]`` for all envs (``mode: add``), or
``func(env, data, **params)`` rewriting an existing entry (``mode: modify``).

The env starts each observation from ``robot/qpos``, ``robot/qvel`` and ``robot/qf`` (the robot's joint
positions, velocities and actuator forces); the task file's terms then modify or add entries, and the
dict is flattened with keys sorted at every level.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from rlexp.config.native_task import (
    Entity,
    Flag,
    Interval,
    JointIds,
    Number,
    OrNull,
    Part,
    Text,
    Vector,
)
from rlexp.envs.native.kinematics import quat_to_mat
from rlexp.envs.native.registry import Registry

if TYPE_CHECKING:
    from rlexp.envs.native.state import SimState

OBSERVATIONS: Registry = Registry("observation func")


def _pose(pos: np.ndarray, rot: np.ndarray, to_matrix: bool) -> np.ndarray:
    """[N, 4, 4] homogeneous matrices, or [N, 7] position + quaternion (w, x, y, z)."""
    if not to_matrix:
        from rlexp.envs.native.kinematics import mat_to_quat

        return np.concatenate([pos, mat_to_quat(rot)], axis=-1)
    out = np.zeros((pos.shape[0], 4, 4))
    out[:, :3, :3] = rot
    out[:, :3, 3] = pos
    out[:, 3, 3] = 1.0
    return out


@OBSERVATIONS.register(
    params={
        "joint_ids": OrNull(JointIds(), "all robot joints; each must have finite limits"),
        "limit": Text(choices=("qpos_limits",)),
        "range": Interval(strict=True),
    }
)
def normalize_robot_joint_data(
    env: SimState,
    data: np.ndarray,
    joint_ids: Sequence[int] | None = None,
    limit: str = "qpos_limits",
    range: Sequence[float] = (0.0, 1.0),  # noqa: A002 - the task files' parameter name
) -> np.ndarray:
    """Map the robot joints ``joint_ids`` of ``data`` linearly from their limits onto ``range``."""
    if limit != "qpos_limits":
        raise ValueError(
            f"normalize_robot_joint_data: limit={limit!r} is not supported (use 'qpos_limits')"
        )
    ids = slice(None) if joint_ids is None else list(joint_ids)
    low, high = env.robot_joint_limits[ids, 0], env.robot_joint_limits[ids, 1]
    if not (np.isfinite(low).all() and np.isfinite(high).all()):
        names = np.asarray(env.task_spec.robot_joints)[ids][~(np.isfinite(low) & np.isfinite(high))]
        raise ValueError(
            f"params.joint_ids: joint(s) {names.tolist()} have no limits to normalise by; "
            "leave them out of joint_ids"
        )
    out = np.array(data, dtype=np.float64, copy=True)
    out[:, ids] = (out[:, ids] - low) / (high - low) * (range[1] - range[0]) + range[0]
    return out


@OBSERVATIONS.register(
    params={
        "part_name": OrNull(Part(), "the task's end effector"),
        "position_only": Flag(),
        "to_matrix": Flag(),
    }
)
def get_robot_eef_pose(
    env: SimState,
    part_name: str | None = None,
    position_only: bool = False,
    to_matrix: bool = True,
) -> np.ndarray:
    """End-effector (tool tip) pose: [N, 4, 4] by default, [N, 3] with ``position_only``."""
    env.check_part(part_name)
    pos, rot = env.ee_pose()
    return pos.copy() if position_only else _pose(pos, rot, to_matrix)


@OBSERVATIONS.register(params={"entity_cfg": Entity(), "to_matrix": Flag()})
def get_rigid_object_pose(
    env: SimState, entity_cfg: dict[str, Any], to_matrix: bool = True
) -> np.ndarray:
    """World pose of a rigid object: [N, 4, 4] by default, [N, 7] (pos, quat wxyz) otherwise."""
    pos, quat = env.object_pose(entity_cfg["uid"])
    if not to_matrix:
        return np.concatenate([pos, quat], axis=-1)
    return _pose(pos, quat_to_mat(quat), True)


@OBSERVATIONS.register(params={"target_pose_key": Text()})
def target_position(env: SimState, target_pose_key: str = "goal_pose") -> np.ndarray:
    """A target position [N, 3] stored by a ``randomize_target_pose`` event."""
    return env.target(target_pose_key).copy()


@OBSERVATIONS.register(params={"joint_ids": OrNull(JointIds(), "all robot joints")})
def get_robot_joint_velocity(env: SimState, joint_ids: Sequence[int] | None = None) -> np.ndarray:
    """Robot joint velocities [N, k] (all robot joints by default)."""
    qvel = env.robot_qvel()
    return qvel if joint_ids is None else qvel[:, list(joint_ids)]


@OBSERVATIONS.register(params={"entity_cfg": Entity(), "angular": Flag()})
def get_rigid_object_velocity(
    env: SimState, entity_cfg: dict[str, Any], angular: bool = False
) -> np.ndarray:
    """A rigid object's linear velocity [N, 3] (world frame; m/s), or with ``angular`` its angular
    velocity [N, 3] (the object's frame; rad/s): simulator state a real robot rarely measures
    (push_cube's ``critic`` group)."""
    linear, spin = env.object_velocity(entity_cfg["uid"])
    return (spin if angular else linear).copy()


@OBSERVATIONS.register(
    params={"entity_cfg": Entity(), "target_pose_key": Text(), "use_xy_only": Flag()}
)
def object_to_target_offset(
    env: SimState,
    entity_cfg: dict[str, Any],
    target_pose_key: str = "goal_pose",
    use_xy_only: bool = False,
) -> np.ndarray:
    """The stored target's position minus the object's, [N, 3] (world frame; [N, 2] with
    ``use_xy_only``): how far, and which way, the object still has to go."""
    pos, _ = env.object_pose(entity_cfg["uid"])
    offset = env.target(target_pose_key) - pos
    return offset[:, :2].copy() if use_xy_only else offset


#: The side of a camera image, in pixels (the smallest a CNN can take, the largest the scenes'
#: offscreen buffers hold: push_cube.xml has 1280 x 960).
IMAGE_SIDE = Number(ge=8, le=960, integer=True, note=" (pixels)")


@OBSERVATIONS.register(
    params={
        "width": IMAGE_SIDE,
        "height": IMAGE_SIDE,
        "eye": OrNull(Vector(), "the task's render camera"),
        "target": OrNull(Vector(), "the task's render camera"),
        "fovy": OrNull(Number(gt=0, lt=180, note=" (degrees)"), "the model's field of view"),
        "camera": OrNull(Text(), "a free camera at eye, looking at target"),
    }
)
def camera_image(
    env: SimState,
    width: int = 64,
    height: int = 64,
    eye: Sequence[float] | None = None,
    target: Sequence[float] | None = None,
    fovy: float | None = None,
    camera: str | None = None,
) -> np.ndarray:
    """Every env's RGB image [N, height, width, 3] uint8 from a free camera at ``eye`` looking at
    ``target`` (MuJoCo's offscreen renderer, ``MUJOCO_GL=egl``; the goal marker is drawn; no
    shadows, reflections or skybox): an
    image entry of the observation, [N, 3, height, width] to the policy (docs/envs.md).
    ``camera``: the model's camera of that name instead (e.g. push_cube's ``wrist``, on the arm)."""
    if camera is not None and (eye, target, fovy) != (None, None, None):
        raise ValueError(
            f"params.camera={camera!r} is the model's camera (its pose and field of view); "
            "leave out eye, target and fovy, or leave out camera"
        )
    if camera is not None and camera not in (have := _cameras(env.model)):
        raise ValueError(
            f"params.camera={camera!r} is not a camera of the model (its cameras: {have})"
        )
    frames = np.empty((env.num_envs, int(height), int(width), 3), dtype=np.uint8)
    view = {"eye": None if eye is None else tuple(eye), "fovy": fovy, "effects": False}
    view["camera"] = camera
    view["target"] = None if target is None else tuple(target)
    for i in range(env.num_envs):
        frames[i] = env.render(i, int(width), int(height), **view)
    return frames


def _cameras(model: Any) -> list[str]:
    """The names of the model's cameras (``camera_image``'s ``camera`` choices)."""
    return [model.camera(i).name for i in range(model.ncam)]
