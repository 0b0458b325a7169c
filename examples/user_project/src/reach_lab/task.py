"""The PointReach task: its scene (assets/point_reach.xml), robot joints and success rule."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rlexp.config.native_task import Number
from rlexp.envs.native import TaskSpec

#: The MJCF inside this package; an absolute path (rlexp's own tasks name files in its assets/).
ASSET = str(Path(__file__).resolve().parent / "assets" / "point_reach.xml")


def distance_to_goal(env, target_pose_key: str = "goal_pose") -> np.ndarray:
    """[N] distance in the table plane between the puck and the stored goal."""
    d = env.robot_qpos()[:, :2] - env.target(target_pose_key)[:, :2]
    return np.sqrt(np.einsum("ij,ij->i", d, d))


def reached(env) -> np.ndarray:
    """The puck is within ``extensions.success_threshold`` of the goal."""
    return distance_to_goal(env) < float(env.extensions["success_threshold"])


POINT_REACH = TaskSpec(
    name="point_reach",
    asset=ASSET,
    robot_joints=("slide_x", "slide_y"),
    parts={"arm": ("slide_x", "slide_y")},
    init_qpos=(0.0, 0.0),
    substeps=2,  # 0.01 s timestep x 2 = 0.02 s per action
    max_episode_steps=50,
    success=reached,
    extensions={"success_threshold": 0.05},
    extension_rules={"success_threshold": Number(gt=0, note=" (m, puck-goal distance)")},
)
