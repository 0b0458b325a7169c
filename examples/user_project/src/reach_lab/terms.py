"""A reward term of this project: ``func(env, **params) -> [N]``, for all envs at once."""

from __future__ import annotations

import numpy as np
from rlexp.config.native_task import Number, Text

from reach_lab.task import distance_to_goal

#: The rule of each parameter, checked when the env is built (a bad value fails before the run).
GOAL_PROXIMITY_PARAMS = {
    "target_pose_key": Text(),
    "scale": Number(gt=0, note=" (1/m)"),
}


def goal_proximity(env, target_pose_key: str = "goal_pose", scale: float = 5.0) -> np.ndarray:
    """1 - tanh(scale * d), d the puck-goal distance: 1 on the goal, towards 0 far from it."""
    return 1.0 - np.tanh(scale * distance_to_goal(env, target_pose_key))
