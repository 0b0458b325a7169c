"""Event terms: ``func(env, env_ids, **params)``, fired on the envs ``env_ids`` (an int array).

``mode: reset`` fires after the envs in ``env_ids`` were put back to their initial state (inside
``step()`` for finished envs, or on ``reset()``); ``startup`` fires once when the env is built;
``interval`` fires on all envs every ``interval_step`` env steps. Random draws come from ``env.rng``
in a fixed order, so the same seed gives the same episodes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from rlexp.config.native_task import Box, Entity, Flag, Interval, JointIds, OrNull, Text
from rlexp.envs.native.registry import Registry

if TYPE_CHECKING:
    from rlexp.envs.native.state import SimState

EVENTS: Registry = Registry("event func")


def _uniform(env: SimState, n: int, position_range: Sequence[Sequence[float]]) -> np.ndarray:
    low, high = np.asarray(position_range[0], float), np.asarray(position_range[1], float)
    return env.rng.uniform(low, high, size=(n, 3))


#: Rules of the pose events' parameters (the built-in events randomize_object_pose /
#: randomize_goal_pose take the same ones).
OBJECT_POSE_PARAMS = {
    "entity_cfg": Entity(),
    "position_range": Box(),
    "relative_position": Flag(),
    "rotation_range": OrNull(Box(), "keep the initial orientation"),
}
TARGET_POSE_PARAMS = {
    "position_range": Box(),
    "relative_position": Flag(),
    "store_key": Text(),
}


@EVENTS.register(params=OBJECT_POSE_PARAMS)
def randomize_rigid_object_pose(
    env: SimState,
    env_ids: np.ndarray,
    entity_cfg: dict[str, Any],
    position_range: Sequence[Sequence[float]],
    relative_position: bool = True,
    rotation_range: Sequence[Sequence[float]] | None = None,
) -> None:
    """Place the object uniformly in ``position_range`` (added to its initial position if relative).

    ``rotation_range`` ([[rx, ry, rz], [rx, ry, rz]], radians, xyz Euler) optionally draws an
    orientation; without it the object keeps its initial orientation. Velocities are zeroed.
    """
    uid = entity_cfg["uid"]
    pos = _uniform(env, len(env_ids), position_range)
    init_pos, init_quat = env.object_initial_pose(uid)
    if relative_position:
        pos = pos + init_pos
    quat = np.broadcast_to(init_quat, (len(env_ids), 4)).copy()
    if rotation_range is not None:
        euler = env.rng.uniform(rotation_range[0], rotation_range[1], size=(len(env_ids), 3))
        quat = _euler_xyz_to_quat(euler)
    env.set_object_pose(uid, env_ids, pos, quat)


@EVENTS.register(params=TARGET_POSE_PARAMS)
def randomize_target_pose(
    env: SimState,
    env_ids: np.ndarray,
    position_range: Sequence[Sequence[float]],
    relative_position: bool = False,
    store_key: str = "target_pose",
) -> None:
    """Draw a target position uniformly in ``position_range``; stored as ``env.target(store_key)``."""
    pos = _uniform(env, len(env_ids), position_range)
    if relative_position:
        pos = pos + env.target(store_key)[env_ids]
    env.set_target(store_key, env_ids, pos)


@EVENTS.register(
    params={
        "position_range": Interval(),
        "joint_ids": OrNull(JointIds(), "all robot joints"),
        "velocity_range": OrNull(Interval(), "velocities stay 0"),
    }
)
def randomize_joint_positions(
    env: SimState,
    env_ids: np.ndarray,
    position_range: Sequence[float],
    joint_ids: Sequence[int] | None = None,
    velocity_range: Sequence[float] | None = None,
) -> None:
    """Add uniform noise in ``position_range`` ([low, high]) to the robot's initial joint positions.

    Not in the users' files; rlexp's ``cart_pole`` config uses it so that episodes differ.
    """
    ids = np.arange(env.num_robot_joints) if joint_ids is None else np.asarray(joint_ids)
    noise = env.rng.uniform(position_range[0], position_range[1], size=(len(env_ids), len(ids)))
    qpos = env.robot_qpos()[env_ids]
    qpos[:, ids] += noise
    qvel = None
    if velocity_range is not None:
        qvel = env.robot_qvel()[env_ids]
        qvel[:, ids] += env.rng.uniform(
            velocity_range[0], velocity_range[1], size=(len(env_ids), len(ids))
        )
    env.set_robot_state(env_ids, qpos, qvel)


def _euler_xyz_to_quat(euler: np.ndarray) -> np.ndarray:
    """Quaternions (w, x, y, z) of intrinsic x-y-z Euler angles [N, 3]."""
    half = 0.5 * euler
    c, s = np.cos(half), np.sin(half)
    cx, cy, cz, sx, sy, sz = c[:, 0], c[:, 1], c[:, 2], s[:, 0], s[:, 1], s[:, 2]
    return np.stack(
        [
            cx * cy * cz - sx * sy * sz,
            sx * cy * cz + cx * sy * sz,
            cx * sy * cz - sx * cy * sz,
            cx * cy * sz + sx * sy * cz,
        ],
        axis=-1,
    )
