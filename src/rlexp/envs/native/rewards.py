"""Reward terms: ``func(env, **params) -> [N]``, evaluated after the physics step for all envs.

The env multiplies each by its ``weight`` and sums them; ``rewards/<term>`` reports each weighted
contribution. Penalties return negative values (a positive weight keeps them negative), as in the
task files: ``action_penalty`` has weight +0.01 on ``action_smoothness_penalty`` = -|a_t - a_{t-1}|.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from rlexp.config.native_task import Entity, Flag, JointIds, Number, OrNull, Part, Text
from rlexp.envs.native.registry import Registry

if TYPE_CHECKING:
    from rlexp.envs.native.state import SimState

REWARDS: Registry = Registry("reward func")


@REWARDS.register(
    params={
        "object_cfg": Entity(),
        "target_pose_key": Text(),
        "behind_offset": Number(ge=0, note=" (m behind the object, away from the target)"),
        "height_offset": Number(note=" (m above the object's centre)"),
        "distance_scale": Number(gt=0, note=" (1/m)"),
        "part_name": OrNull(Part(), "the task's end effector"),
    }
)
def reaching_behind_object(
    env: SimState,
    object_cfg: dict[str, Any],
    target_pose_key: str = "goal_pose",
    behind_offset: float = 0.015,
    height_offset: float = 0.015,
    distance_scale: float = 5.0,
    part_name: str | None = None,
) -> np.ndarray:
    """1 - tanh(scale * d), d = |tool - (object - behind_offset * dir(object->goal) + height_offset z)|."""
    env.check_part(part_name)
    ee_pos, _ = env.ee_pose()
    obj_pos, _ = env.object_pose(object_cfg["uid"])
    push = env.target(target_pose_key) - obj_pos
    push_dir = push / (np.linalg.norm(push, axis=-1, keepdims=True) + 1e-6)
    behind = obj_pos - behind_offset * push_dir
    behind[:, 2] += height_offset
    return 1.0 - np.tanh(distance_scale * np.linalg.norm(ee_pos - behind, axis=-1))


@REWARDS.register(
    params={
        "source_entity_cfg": Entity(),
        "target_pose_key": Text(),
        "exponential": Flag(),
        "sigma": Number(gt=0, note=" (m)"),
        "use_xy_only": Flag(),
    }
)
def distance_to_target(
    env: SimState,
    source_entity_cfg: dict[str, Any],
    target_pose_key: str = "target_pose",
    exponential: bool = False,
    sigma: float = 1.0,
    use_xy_only: bool = False,
) -> np.ndarray:
    """exp(-d^2 / (2 sigma^2)) if ``exponential`` else -d, d = |object - target| (xy only if asked)."""
    obj_pos, _ = env.object_pose(source_entity_cfg["uid"])
    diff = obj_pos - env.target(target_pose_key)
    if use_xy_only:
        diff = diff[:, :2]
    d2 = np.einsum("ij,ij->i", diff, diff)
    return np.exp(-d2 / (2.0 * sigma**2)) if exponential else -np.sqrt(d2)


@REWARDS.register(params={})
def action_smoothness_penalty(env: SimState) -> np.ndarray:
    """-|a_t - a_{t-1}| (L2 norm of the clipped actions); 0 on the first step of an episode."""
    delta = env.action - env.prev_action
    penalty = -np.sqrt(np.einsum("ij,ij->i", delta, delta))
    penalty[env.episode_step == 1] = 0.0
    return penalty


@REWARDS.register(params={})
def success_reward(env: SimState) -> np.ndarray:
    """1 where the task reports success this step, else 0."""
    return env.success.astype(np.float64)


@REWARDS.register(
    params={
        "robot_uid": OrNull(Text(), "the task's robot; a task has one robot, so it is not used"),
        "joint_ids": OrNull(JointIds(), "the part's joints, else all robot joints"),
        "part_name": OrNull(Part(), "all robot joints"),
    }
)
def joint_velocity_penalty(
    env: SimState,
    robot_uid: str | None = None,
    joint_ids: Sequence[int] | None = None,
    part_name: str | None = None,
) -> np.ndarray:
    """-|qvel| (L2 norm) over ``joint_ids``, else the joints of ``part_name``, else all robot joints."""
    qvel = env.robot_qvel()
    if joint_ids is not None:
        qvel = qvel[:, list(joint_ids)]
    elif part_name is not None:
        qvel = qvel[:, env.part_joint_ids(part_name)]
    return -np.sqrt(np.einsum("ij,ij->i", qvel, qvel))


@REWARDS.register(params={"joint_ids": JointIds()})
def upright_reward(env: SimState, joint_ids: Sequence[int] = (1,)) -> np.ndarray:
    """cos of the hinge angle(s) (mean over ``joint_ids``): 1 with the pole upright, 0 when horizontal.

    Not in the users' CartPole file (it has only ``joint_velocity_penalty``, which alone teaches
    nothing); rlexp's ``cart_pole`` config adds it so the task is learnable.
    """
    return np.cos(env.robot_qpos()[:, list(joint_ids)]).mean(axis=-1)


@REWARDS.register(params={})
def alive_bonus(env: SimState) -> np.ndarray:
    """1 for every step that does not end the episode by termination."""
    return (~env.terminated).astype(np.float64)
