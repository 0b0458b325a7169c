"""The MuJoCo state of N envs of one task, and the accessors the terms read and write it through.

``SimState`` holds the batched physics state (``[N, nstate]`` rows of ``mjSTATE_FULLPHYSICS``, with
``qpos`` / ``qvel`` views into it), the index tables that locate the robot's joints, the actuators
and the rigid objects in it, and the per-env episode flags. Observation, reward, event and action
terms, task rules and parameter rules see the env as a ``SimState``; ``NativeEnv`` builds on it
(physics stepping, terms, specs, resets, resume) and sets the attributes listed below as its own.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from rlexp.config.native_task import Vector
from rlexp.envs.native.kinematics import SerialChainFK
from rlexp.envs.native.registry import unknown_name_message


class _StepVars:
    """Per-step scalars and caches, kept off the env: EnvBase/nn.Module attribute writes are slow."""

    def __init__(self) -> None:
        self.version = 0  # bumped whenever the physics state changes; invalidates cached kinematics
        self.fk_version = -1
        self.fk_cache: tuple[np.ndarray, np.ndarray] | None = None
        # every env's observation now (post-reset for reset envs)
        self.current_obs: np.ndarray | None = None
        self.current_images: dict[str, np.ndarray] = {}  # a camera term's uint8 [N, C, H, W]
        self.interval_count = 0


class SimState:
    """The state of ``num_envs`` copies of one MuJoCo task and the accessors terms use on it."""

    # set by NativeEnv before _setup_indices / _setup_state
    model: mujoco.MjModel
    task_spec: Any  # the task's TaskSpec: tasks.py imports this module (its rules take a SimState)
    num_envs: int
    max_episode_steps: int  # the time limit (truncation)
    extensions: dict[str, Any]  # env.extensions: the task's defaults and the config's values
    rng: np.random.Generator  # the env's generator (set_seed): events draw from it in a fixed order
    # set by NativeEnv with its action terms
    action: np.ndarray  # [N, A] the current (clipped) action
    prev_action: np.ndarray  # [N, A] the previous step's action

    # ------------------------------------------------------------------ setup

    def _setup_indices(self, scene: dict[str, Any]) -> None:
        """Where the robot's joints, the actuators and the rigid objects sit in the state; checks the
        scene's ``init_qpos`` and that the actuators are of the kinds ``robot_qf`` computes."""
        m, task = self.model, self.task_spec
        self.robot_joint_ids = np.array([m.joint(j).id for j in task.robot_joints])
        self.robot_qpos_adr = m.jnt_qposadr[self.robot_joint_ids]
        self.robot_dof_adr = m.jnt_dofadr[self.robot_joint_ids]
        self.num_robot_joints = len(self.robot_joint_ids)
        limited = m.jnt_limited[self.robot_joint_ids].astype(bool)
        self.robot_joint_limits = np.where(
            limited[:, None], m.jnt_range[self.robot_joint_ids], [-np.inf, np.inf]
        )
        raw = scene.get("init_qpos", task.init_qpos)
        if isinstance(raw, (list, tuple)) and len(raw) != self.num_robot_joints:
            raise ValueError(
                f"env.native.scene.init_qpos has {len(raw)} values; {task.name} has "
                f"{self.num_robot_joints} robot joints {list(task.robot_joints)}"
            )
        Vector(names=tuple(task.robot_joints)).check(list(raw), "env.native.scene.init_qpos")
        init_qpos = np.asarray(raw, float)
        low, high = self.robot_joint_limits[:, 0], self.robot_joint_limits[:, 1]
        outside = np.flatnonzero((init_qpos < low) | (init_qpos > high))
        if outside.size:
            j = int(outside[0])
            raise ValueError(
                f"env.native.scene.init_qpos={init_qpos.tolist()}: {task.robot_joints[j]}="
                f"{init_qpos[j]:g} is outside the joint's range [{low[j]:g}, {high[j]:g}]"
            )
        self.robot_init_qpos = init_qpos
        # actuators: joint transmission only, fixed gain, affine or no bias (position servos, motors)
        if not (m.actuator_trntype == mujoco.mjtTrn.mjTRN_JOINT).all():
            raise ValueError(f"{task.asset}: every actuator must drive a joint")
        if (
            not (m.actuator_dyntype == mujoco.mjtDyn.mjDYN_NONE).all()
            or not (m.actuator_gaintype == mujoco.mjtGain.mjGAIN_FIXED).all()
        ):
            raise ValueError(f"{task.asset}: actuators must have no dynamics and a fixed gain")
        act_joint = m.actuator_trnid[:, 0]
        self.actuator_qpos_adr = m.jnt_qposadr[act_joint]
        self._act_dof_adr = m.jnt_dofadr[act_joint]
        self._act_gear = m.actuator_gear[:, 0].copy()
        self._act_gain = m.actuator_gainprm[:, 0].copy()
        self._act_bias = m.actuator_biasprm[:, :3].copy()
        limited = m.actuator_forcelimited.astype(bool)
        self._act_force_low = np.where(limited, m.actuator_forcerange[:, 0], -np.inf)
        self._act_force_high = np.where(limited, m.actuator_forcerange[:, 1], np.inf)
        # robot dof -> column in the robot's qf observation, for each actuator (-1: not a robot joint)
        dof_to_robot = {int(d): i for i, d in enumerate(self.robot_dof_adr)}
        cols = np.array([dof_to_robot.get(int(d), -1) for d in self._act_dof_adr])
        if len(set(cols[cols >= 0])) != int((cols >= 0).sum()):
            raise ValueError(f"{task.asset}: at most one actuator per robot joint")
        self._act_robot_valid = cols >= 0
        self._act_robot_col_valid = cols[cols >= 0]
        # rigid objects: free joints
        self._object_qpos_adr: dict[str, int] = {}
        self._object_dof_adr: dict[str, int] = {}
        for uid, body in task.objects.items():
            b = m.body(body)
            j = int(m.body_jntadr[b.id])
            if j < 0 or m.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE:
                raise ValueError(f"{task.asset}: object {uid!r} (body {body!r}) needs a free joint")
            self._object_qpos_adr[uid] = int(m.jnt_qposadr[j])
            self._object_dof_adr[uid] = int(m.jnt_dofadr[j])
        self._fk = SerialChainFK(m, task.ee_site) if task.ee_site else None

    def _setup_state(self) -> None:
        """The state layout (checked against ``mj_getState``), the initial state and the arrays."""
        m, n = self.model, self.num_envs
        self._nstate = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        # the full physics state begins with time, qpos, qvel, act (checked against mj_getState)
        self._sl_qpos = slice(1, 1 + m.nq)
        self._sl_qvel = slice(1 + m.nq, 1 + m.nq + m.nv)
        self._sl_act = slice(1 + m.nq + m.nv, 1 + m.nq + m.nv + m.na)
        data = mujoco.MjData(m)
        data.time, data.qpos[:], data.qvel[:] = 0.25, np.arange(m.nq) + 0.5, np.arange(m.nv) + 0.75
        probe = np.empty(self._nstate)
        mujoco.mj_getState(m, data, probe, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        if (
            probe[0] != 0.25
            or not np.array_equal(probe[self._sl_qpos], data.qpos)
            or not np.array_equal(probe[self._sl_qvel], data.qvel)
        ):
            raise RuntimeError("unexpected mjSTATE_FULLPHYSICS layout in this MuJoCo version")
        mujoco.mj_resetData(m, data)
        mujoco.mj_getState(m, data, probe, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        self._init_state = probe.copy()
        self._init_state[self._sl_qpos][self.robot_qpos_adr] = self.robot_init_qpos
        self._init_ctrl = np.zeros(m.nu)
        self._init_ctrl[:] = self._init_state[self._sl_qpos][self.actuator_qpos_adr]

        self._state = np.tile(self._init_state, (n, 1))  # [N, nstate]: the envs' physics state
        self._ctrl = np.tile(self._init_ctrl, (n, 1))  # [N, nu]
        self.qpos = self._state[:, self._sl_qpos]  # views into the state
        self.qvel = self._state[:, self._sl_qvel]
        self._v = _StepVars()

        self.episode_step = np.zeros(n, dtype=np.int64)  # steps taken in the current episode
        self.success = np.zeros(n, dtype=bool)
        self.terminated = np.zeros(n, dtype=bool)
        self.truncated = np.zeros(n, dtype=bool)
        self._targets: dict[str, np.ndarray] = {}

    # ------------------------------------------------------------------ accessors for the terms

    def robot_qpos(self) -> np.ndarray:
        """Robot joint positions [N, k] (a copy)."""
        return self.qpos[:, self.robot_qpos_adr]

    def robot_qvel(self) -> np.ndarray:
        """Robot joint velocities [N, k] (a copy)."""
        return self.qvel[:, self.robot_dof_adr]

    def robot_qf(self) -> np.ndarray:
        """Actuator forces on the robot joints [N, k], as ``qfrc_actuator`` after ``mj_forward``."""
        length = self._act_gear * self.qpos[:, self.actuator_qpos_adr]
        velocity = self._act_gear * self.qvel[:, self._act_dof_adr]
        force = self._act_gain * self._ctrl + self._act_bias[:, 0] + self._act_bias[:, 1] * length
        force += self._act_bias[:, 2] * velocity
        np.minimum(force, self._act_force_high, out=force)
        np.maximum(force, self._act_force_low, out=force)
        out = np.zeros((self.num_envs, self.num_robot_joints))
        out[:, self._act_robot_col_valid] = (self._act_gear * force)[:, self._act_robot_valid]
        return out

    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """End-effector site position [N, 3] and rotation [N, 3, 3] (cached until the state changes)."""
        if self._fk is None:
            raise ValueError(f"task {self.task_spec.name!r} has no end-effector site")
        v = self._v
        if v.fk_version != v.version:
            v.fk_cache = self._fk(self.qpos)
            v.fk_version = v.version
        return v.fk_cache  # type: ignore[return-value]

    def object_pose(self, uid: str) -> tuple[np.ndarray, np.ndarray]:
        """Position [N, 3] and quaternion [N, 4] (w, x, y, z) of rigid object ``uid`` (views)."""
        try:
            adr = self._object_qpos_adr[uid]
        except KeyError:
            raise KeyError(
                unknown_name_message("rigid object uid", uid, self._object_qpos_adr)
            ) from None
        return self.qpos[:, adr : adr + 3], self.qpos[:, adr + 3 : adr + 7]

    def object_velocity(self, uid: str) -> tuple[np.ndarray, np.ndarray]:
        """Linear velocity [N, 3] (world frame) and angular velocity [N, 3] (the body's frame) of
        rigid object ``uid``: its free joint's qvel (views)."""
        self.object_pose(uid)  # validates uid
        adr = self._object_dof_adr[uid]
        return self.qvel[:, adr : adr + 3], self.qvel[:, adr + 3 : adr + 6]

    def object_initial_pose(self, uid: str) -> tuple[np.ndarray, np.ndarray]:
        """The object's initial position [3] and quaternion [4] (from the scene)."""
        self.object_pose(uid)  # validates uid
        adr = self._object_qpos_adr[uid]
        q0 = self._init_state[self._sl_qpos]
        return q0[adr : adr + 3].copy(), q0[adr + 3 : adr + 7].copy()

    def target(self, key: str) -> np.ndarray:
        """A stored target position [N, 3] (set by a ``randomize_target_pose`` event)."""
        try:
            return self._targets[key]
        except KeyError:
            raise KeyError(
                f"target pose {key!r} is not stored; add a randomize_target_pose event with "
                f"store_key={key!r} (stored: {sorted(self._targets)})"
            ) from None

    def set_target(self, key: str, env_ids: np.ndarray, pos: np.ndarray) -> None:
        """Store target position(s) ``pos`` for envs ``env_ids`` under ``key``."""
        if key not in self._targets:
            self._targets[key] = np.zeros((self.num_envs, 3))
        self._targets[key][env_ids] = pos

    def set_object_pose(
        self, uid: str, env_ids: np.ndarray, pos: np.ndarray, quat: np.ndarray
    ) -> None:
        """Place object ``uid`` in envs ``env_ids`` at rest."""
        self.object_pose(uid)
        qa, da = self._object_qpos_adr[uid], self._object_dof_adr[uid]
        self.qpos[env_ids, qa : qa + 3] = pos
        self.qpos[env_ids, qa + 3 : qa + 7] = quat
        self.qvel[env_ids, da : da + 6] = 0.0
        self._v.version += 1

    def set_robot_state(
        self, env_ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray | None = None
    ) -> None:
        """Set robot joint positions (and velocities) in envs ``env_ids``; servo targets follow."""
        rows = np.asarray(env_ids)[:, None]
        self.qpos[rows, self.robot_qpos_adr] = qpos
        self.qvel[rows, self.robot_dof_adr] = 0.0 if qvel is None else qvel
        self._ctrl[rows, np.arange(self.model.nu)] = self.qpos[rows, self.actuator_qpos_adr]
        self._v.version += 1

    def part_joint_ids(self, part_name: str) -> list[int]:
        """Indices (into the robot's joints) of the joints of control part ``part_name``."""
        self.check_part(part_name)
        return [self.task_spec.robot_joints.index(j) for j in self.task_spec.parts[part_name]]

    def check_part(self, part_name: str | None) -> None:
        """KeyError naming the choices unless ``part_name`` is None or a control part of the task."""
        if part_name is not None and part_name not in self.task_spec.parts:
            raise KeyError(unknown_name_message("control part", part_name, self.task_spec.parts))

    def actuators_of_part(self, part_name: str | None) -> np.ndarray:
        """Actuator ids driving the joints of ``part_name`` (all actuators if None)."""
        if part_name is None:
            return np.arange(self.model.nu)
        self.check_part(part_name)
        joints = {self.model.joint(j).id for j in self.task_spec.parts[part_name]}
        return np.array(
            [a for a in range(self.model.nu) if int(self.model.actuator_trnid[a, 0]) in joints]
        )
