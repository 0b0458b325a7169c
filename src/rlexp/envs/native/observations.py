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

from rlexp.config.native_task import Entity, Flag, Interval, JointIds, OrNull, Part, Text
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
