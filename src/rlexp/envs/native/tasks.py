"""The native tasks: which MJCF scene, which joints form the robot, and how an episode ends.

A task is a scene (``assets/<name>.xml``) plus a term configuration (``NativeTaskConfig``: events,
observations, rewards, actions, extensions). ``TASKS`` maps the config's ``task`` name onto the scene
side; ``default_task_config(name)`` gives the term side, the same as ``conf/env/<name>.yaml``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from rlexp.config.native_task import (
    ActionTermConfig,
    EventTermConfig,
    NativeTaskConfig,
    Number,
    ObservationTermConfig,
    ParamRule,
    RewardTermConfig,
)
from rlexp.envs.native.registry import Registry

if TYPE_CHECKING:
    from rlexp.envs.native.state import SimState


@dataclass(frozen=True)
class TaskSpec:
    """The scene side of a task."""

    name: str
    asset: str  # MJCF file in rlexp/envs/native/assets/
    robot_joints: tuple[str, ...]  # the robot's joints, in observation order
    parts: dict[str, tuple[str, ...]]  # control parts ("arm", "hand") -> joint names
    init_qpos: tuple[float, ...]  # initial robot joint positions (scene.init_qpos overrides)
    objects: dict[str, str] = field(
        default_factory=dict
    )  # rigid object uid -> its body (with a free joint)
    ee_site: str | None = None  # end-effector site (tool tip), for get_robot_eef_pose
    substeps: int = 1  # physics steps per env step
    max_episode_steps: int = 100  # time limit (truncation) unless the config overrides it
    # per-env flags computed after each step, in this order: success, terminated, truncated (besides the time limit)
    success: Callable[[SimState], np.ndarray] | None = None
    terminated: Callable[[SimState], np.ndarray] | None = None
    truncated: Callable[[SimState], np.ndarray] | None = None
    extensions: dict[str, Any] = field(default_factory=dict)  # defaults for env.extensions
    # rules of the extensions the task reads (other keys of env.extensions are free values)
    extension_rules: dict[str, ParamRule] = field(default_factory=dict)
    camera: dict[str, tuple[float, float, float]] = field(
        default_factory=dict
    )  # default render eye/target
    markers: dict[str, str] = field(
        default_factory=dict
    )  # mocap body -> stored target it shows (render only)


TASKS: Registry = Registry("native task")


# --- PushCube --------------------------------------------------------------------------------------


def _push_cube_success(env: SimState) -> np.ndarray:
    """The cube's centre is within ``success_threshold`` of the goal in xy."""
    cube, _ = env.object_pose("cube")
    d = cube[:, :2] - env.target("goal_pose")[:, :2]
    return np.einsum("ij,ij->i", d, d) < float(env.extensions["success_threshold"]) ** 2


def _push_cube_fell(env: SimState) -> np.ndarray:
    """The cube left the table (fell below ``cube_min_z``): the episode cannot go on, so truncate."""
    cube, _ = env.object_pose("cube")
    return cube[:, 2] < float(env.extensions["cube_min_z"])


UR_ARM_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)

PUSH_CUBE = TaskSpec(
    name="push_cube",
    asset="push_cube.xml",
    robot_joints=UR_ARM_JOINTS,
    parts={"arm": UR_ARM_JOINTS},
    # The file's [0, -1.57, 1.57, -1.57, -1.57, 0] holds the tool 0.49 m up; this bends the elbow
    # further so the tool starts pointing down ~0.15 m above the table, beside the cube's region.
    init_qpos=(0.0, -1.57, 2.2, -2.2, -1.57, 0.0),
    objects={"cube": "cube"},
    ee_site="ee_site",
    substeps=4,  # 0.01 s timestep x 4 = 0.04 s per action
    max_episode_steps=100,
    success=_push_cube_success,
    terminated=_push_cube_success,
    truncated=_push_cube_fell,
    extensions={"success_threshold": 0.1, "cube_min_z": -0.1},
    extension_rules={
        "success_threshold": Number(gt=0, note=" (m, cube-goal distance in xy)"),
        "cube_min_z": Number(note=" (m; below it the episode is truncated)"),
    },
    camera={"eye": (0.6, -1.9, 1.4), "target": (-0.3, -0.2, 0.1)},
    markers={"goal": "goal_pose"},
)
TASKS.register("push_cube")(PUSH_CUBE)


# --- CartPole --------------------------------------------------------------------------------------


def _cart_pole_failed(env: SimState) -> np.ndarray:
    """The pole fell past ``pole_angle_limit`` or the cart left ``+- track_limit``."""
    q = env.robot_qpos()
    return (np.abs(q[:, 1]) > float(env.extensions["pole_angle_limit"])) | (
        np.abs(q[:, 0]) > float(env.extensions["track_limit"])
    )


def _cart_pole_success(env: SimState) -> np.ndarray:
    """Balanced until the time limit: the last step of an episode that was not terminated."""
    return (env.episode_step >= env.max_episode_steps) & ~_cart_pole_failed(env)


CART_POLE = TaskSpec(
    name="cart_pole",
    asset="cart_pole.xml",
    robot_joints=("slider_to_cart", "cart_to_pole"),
    parts={"arm": ("slider_to_cart",), "hand": ("cart_to_pole",)},
    init_qpos=(-0.2, 0.07),  # the file's init_qpos
    substeps=2,  # 0.01 s timestep x 2 = 0.02 s per action, as the classic cart-pole
    max_episode_steps=500,
    success=_cart_pole_success,
    terminated=_cart_pole_failed,
    extensions={"pole_angle_limit": 0.4, "track_limit": 1.8},
    extension_rules={
        "pole_angle_limit": Number(gt=0, note=" (rad)"),
        "track_limit": Number(gt=0, note=" (m)"),
    },
    camera={"eye": (0.0, -4.0, 1.5), "target": (0.0, 0.0, 0.8)},
)
TASKS.register("cart_pole")(CART_POLE)


def get_task(name: str) -> TaskSpec:
    """The registered task ``name`` ("unknown native task 'push_cub' ...; did you mean 'push_cube'?")."""
    return TASKS.get(name, "env.native.task")


# --- default term configurations (mirrors of conf/env/<task>.yaml) ---------------------------------


def default_task_config(name: str) -> NativeTaskConfig:
    """The term configuration of the users' task file for ``name``, as ``conf/env/<name>.yaml`` has it."""
    get_task(name)
    if name == "push_cube":
        return NativeTaskConfig(
            task="push_cube",
            events={
                "randomize_cube": EventTermConfig(
                    func="randomize_rigid_object_pose",
                    mode="reset",
                    params={
                        "entity_cfg": {"uid": "cube"},
                        "position_range": [[-0.2, -0.2, 0.0], [0.2, 0.2, 0.0]],
                        "relative_position": True,
                    },
                ),
                "randomize_goal": EventTermConfig(
                    func="randomize_target_pose",
                    mode="reset",
                    params={
                        "position_range": [[-0.3, -0.3, 0.05], [0.3, 0.3, 0.05]],
                        "relative_position": False,
                        "store_key": "goal_pose",
                    },
                ),
            },
            observations={
                "robot_qpos": ObservationTermConfig(
                    func="normalize_robot_joint_data",
                    mode="modify",
                    name="robot/qpos",
                    params={"joint_ids": [0, 1, 2, 3, 4, 5]},
                ),
                "robot_ee_pos": ObservationTermConfig(
                    func="get_robot_eef_pose",
                    mode="add",
                    name="robot/ee_pos",
                    params={"part_name": "arm"},
                ),
                "cube_pos": ObservationTermConfig(
                    func="get_rigid_object_pose",
                    mode="add",
                    name="object/cube_pos",
                    params={"entity_cfg": {"uid": "cube"}},
                ),
                "goal_pos": ObservationTermConfig(
                    func="target_position",
                    mode="add",
                    name="object/goal_pos",
                    params={"target_pose_key": "goal_pose"},
                ),
                # the critic group: privileged state the actor does not see
                "cube_vel": ObservationTermConfig(
                    func="get_rigid_object_velocity",
                    mode="add",
                    name="privileged/cube_vel",
                    params={"entity_cfg": {"uid": "cube"}},
                    group="critic",
                ),
                "cube_to_goal": ObservationTermConfig(
                    func="object_to_target_offset",
                    mode="add",
                    name="privileged/cube_to_goal",
                    params={"entity_cfg": {"uid": "cube"}, "target_pose_key": "goal_pose"},
                    group="critic",
                ),
            },
            rewards={
                "reaching_reward": RewardTermConfig(
                    func="reaching_behind_object",
                    weight=0.03,
                    params={
                        "object_cfg": {"uid": "cube"},
                        "target_pose_key": "goal_pose",
                        "behind_offset": 0.03,
                        "height_offset": 0.015,
                        "distance_scale": 8.0,
                        "part_name": "arm",
                    },
                ),
                "goal_distance_reward": RewardTermConfig(
                    func="distance_to_target",
                    weight=0.8,
                    params={
                        "source_entity_cfg": {"uid": "cube"},
                        "target_pose_key": "goal_pose",
                        "exponential": True,
                        "sigma": 0.12,
                        "use_xy_only": True,
                    },
                ),
                "action_penalty": RewardTermConfig(func="action_smoothness_penalty", weight=0.01),
                "success_bonus": RewardTermConfig(func="success_reward", weight=10.0),
            },
            actions={"delta_qpos": ActionTermConfig(func="DeltaQposTerm", params={"scale": 0.1})},
            extensions={"success_threshold": 0.1},
        )
    return NativeTaskConfig(
        task="cart_pole",
        events={
            "randomize_start": EventTermConfig(
                func="randomize_joint_positions",
                mode="reset",
                params={"position_range": [-0.05, 0.05]},
            )
        },
        observations={
            "robot_qpos": ObservationTermConfig(
                func="normalize_robot_joint_data",
                mode="modify",
                name="robot/qpos",
                params={"joint_ids": [0, 1]},
            )
        },
        rewards={
            "upright": RewardTermConfig(
                func="upright_reward", weight=1.0, params={"joint_ids": [1]}
            ),
            "velocity_penalty": RewardTermConfig(
                func="joint_velocity_penalty",
                weight=0.005,
                params={"robot_uid": "Cart", "part_name": "hand"},
            ),
        },
        actions={"delta_qpos": ActionTermConfig(func="DeltaQposTerm", params={"scale": 0.1})},
        extensions={},
    )
