"""``NativeEnv``: N copies of one MuJoCo task in one process, as a batched TorchRL env.

Physics for all N envs advances in C with ``mujoco.rollout`` (a persistent thread pool) from one
[N, nstate] numpy state array; observations, rewards and flags are computed for all envs at once in
numpy from that state. No per-env Python object or loop sits in the step.

Auto-reset contract (``step_and_maybe_reset`` / ``Collector``): ``_step`` returns the true final
observation of an env that finished (so truncated episodes can be bootstrapped) and then resets that
env physically, in the same batched way; the ``_reset`` call TorchRL makes next with a ``"_reset"``
mask only hands back the cached post-reset observation for those envs. A plain ``reset()`` resets all.
"""

from __future__ import annotations

import inspect
import logging
import os
from dataclasses import asdict, is_dataclass
from importlib import resources
from typing import Any

import mujoco
import numpy as np
import torch
from mujoco import rollout
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from rlexp.config.native_task import (
    NativeTaskConfig,
    Number,
    ParamRule,
    Unchecked,
    Vector,
    check_params,
    plain,
)
from rlexp.envs.native.actions import ACTIONS
from rlexp.envs.native.events import EVENTS
from rlexp.envs.native.kinematics import SerialChainFK
from rlexp.envs.native.observations import OBSERVATIONS
from rlexp.envs.native.registry import unknown_name_message
from rlexp.envs.native.rewards import REWARDS
from rlexp.envs.native.tasks import TaskSpec, get_task

log = logging.getLogger(__name__)

EVENT_MODES = ("startup", "reset", "interval")
OBSERVATION_MODES = ("add", "modify")
REWARD_MODES = ("add", "replace")
ROBOT_OBSERVATIONS = ("robot/qpos", "robot/qvel", "robot/qf")  # every observation starts from these


def _as_dict(cfg: Any) -> dict[str, Any]:
    """A term entry (dataclass or mapping) as a plain dict."""
    if is_dataclass(cfg):
        return asdict(cfg)
    return dict(cfg)


def _check_params(
    func: Any, params: dict[str, Any], where: str, skip: int, env: Any = None
) -> None:
    """Fail at build time, naming the config key, if ``params`` do not fit ``func``: its rules
    (``PARAMS``, set by the registries: types, lengths, ranges, and with ``env`` the names and joint
    indices they refer to), else at least its signature."""
    target = func.__init__ if isinstance(func, type) else func
    sig = inspect.signature(target)
    names = list(sig.parameters)[skip:]
    required = [n for n in names if sig.parameters[n].default is inspect.Parameter.empty]
    rules = getattr(func, "PARAMS", None)
    if rules is None:
        rules = {n: Unchecked() for n in names}
    check_params(func.__name__, params, rules, f"{where}.params", required, env)


def _friction_ok(value: Any, where: str) -> None:
    values = value if isinstance(value, (list, tuple)) else [value]
    if not 1 <= len(values) <= 3:
        raise ValueError(
            f"{where}={value!r} must be 1 to 3 numbers >= 0 (sliding, torsional, rolling)"
        )
    for i, v in enumerate(values):
        Number(ge=0).check(v, f"{where}[{i}]" if isinstance(value, (list, tuple)) else where)


#: Rules of the scene overrides of a rigid object ``<uid>_<attr>`` (init_qpos: in _setup_indices).
SCENE_RULES: dict[str, ParamRule] = {
    "init_pos": Vector(note="m, world frame"),
    "size": Vector(gt=0, note="m, full edge lengths"),
    "mass": Number(gt=0, note=" (kg)"),
}


_TERM_ERRORS = (KeyError, ValueError, TypeError)


def _named(exc: Exception, where: str) -> Exception:
    """A term's KeyError / ValueError / TypeError with its config key in front of the message
    (``raise _named(exc, where) from exc`` in an ``except _TERM_ERRORS``: free when nothing fails)."""
    msg = str(exc.args[0] if exc.args else exc)
    kind = next(k for k in _TERM_ERRORS if isinstance(exc, k))
    return kind(msg if msg.startswith(where) else f"{where}: {msg}")


def _choose(value: str, choices: tuple[str, ...], where: str) -> str:
    if value not in choices:
        raise ValueError(unknown_name_message("mode", value, choices, where))
    return value


def default_num_threads(num_envs: int) -> int:
    """Physics threads: none (the calling thread) for a few envs, else one per core, at most 16."""
    cores = (
        len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    )
    return 0 if num_envs < 4 or cores < 2 else min(cores, 16, num_envs)


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


class _StepVars:
    """Per-step scalars and caches, kept off the env: EnvBase/nn.Module attribute writes are slow."""

    def __init__(self) -> None:
        self.version = 0  # bumped whenever the physics state changes; invalidates cached kinematics
        self.fk_version = -1
        self.fk_cache: tuple[np.ndarray, np.ndarray] | None = None
        self.current_obs: np.ndarray | None = (
            None  # every env's observation now (post-reset for reset envs)
        )
        self.interval_count = 0


class NativeEnv(EnvBase):
    """A batched MuJoCo task (``batch_size=[num_envs]``) built from a term configuration."""

    def __init__(
        self,
        task_cfg: NativeTaskConfig,
        num_envs: int,
        max_episode_steps: int | None = None,
        device: str | torch.device = "cpu",
        num_threads: int | None = None,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        super().__init__(batch_size=torch.Size([num_envs]), device=device)
        cfg = (
            task_cfg
            if isinstance(task_cfg, NativeTaskConfig)
            else NativeTaskConfig(**_as_dict(task_cfg))
        )
        self.task_spec: TaskSpec = get_task(cfg.task)
        self.task_cfg = cfg
        self.num_envs = num_envs
        self.max_episode_steps = int(max_episode_steps or self.task_spec.max_episode_steps)
        self.extensions: dict[str, Any] = {
            **self.task_spec.extensions,
            **plain(cfg.extensions or {}),
        }
        for key, rule in self.task_spec.extension_rules.items():
            rule.check(self.extensions[key], f"env.native.extensions.{key}")

        self.model, scene = load_model(self.task_spec, plain(cfg.scene or {}))
        self._setup_indices(scene)
        self._setup_physics(num_threads)
        self._setup_terms(cfg)

        # Build-time pass with a throwaway generator: gives every env a valid state and the targets
        # the observation terms read, and fixes the observation layout. set_seed()/reset() follow.
        # Every startup / reset event, observation and reward runs once here, so a parameter that
        # only fails when used (a target no event stores) fails now, naming the term.
        self.rng = np.random.default_rng(0)
        self._fire(self._startup_events, np.arange(num_envs))
        self._reset_envs(np.arange(num_envs))
        obs = self._observation_dict()
        for key, func, _, _, params in self._reward_terms:
            try:
                func(self, **params)
            except _TERM_ERRORS as exc:
                raise _named(exc, f"rewards.{key}") from exc
        self.observation_layout = self._layout(obs)
        self.obs_dim = self.observation_layout[-1][2] if self.observation_layout else 0
        self._v.current_obs = self._flatten(obs)
        self._make_specs()
        log.info(
            "native env %s: %d envs, obs %d, action %d, %d physics steps/action, %d physics threads",
            self.task_spec.name, num_envs, self.obs_dim, self.action_dim, self.substeps, self.num_threads,
        )  # fmt: skip

    # ------------------------------------------------------------------ setup

    def _setup_indices(self, scene: dict[str, Any]) -> None:
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

    def _setup_physics(self, num_threads: int | None) -> None:
        m, n = self.model, self.num_envs
        self.substeps = self.task_spec.substeps
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
        self._control = np.zeros(
            (n, self.substeps, m.nu)
        )  # rollout input: ctrl held over the substeps
        self._traj = np.zeros((n, self.substeps, self._nstate))  # rollout output
        self._sensordata = np.zeros((n, self.substeps, m.nsensordata))
        self.qpos = self._state[:, self._sl_qpos]  # views into the state
        self.qvel = self._state[:, self._sl_qvel]
        self.num_threads = default_num_threads(n) if num_threads is None else int(num_threads)
        self._pool = rollout.Rollout(nthread=self.num_threads)
        self._datas = [mujoco.MjData(m) for _ in range(max(1, self.num_threads))]
        self._models = [m] * n
        self._chunk = max(1, n // (max(1, self.num_threads) * 4))
        self._v = _StepVars()

        self.episode_step = np.zeros(n, dtype=np.int64)  # steps taken in the current episode
        self.success = np.zeros(n, dtype=bool)
        self.terminated = np.zeros(n, dtype=bool)
        self.truncated = np.zeros(n, dtype=bool)
        self._pending_reset = np.zeros(
            n, dtype=bool
        )  # reset inside _step, not yet handed out by _reset
        self._targets: dict[str, np.ndarray] = {}
        self._restored = (
            False  # set by load_env_state: the next full reset hands back the restored state
        )
        self.last_reset_was_restore = False
        self._render_data: mujoco.MjData | None = None
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}

    def _setup_terms(self, cfg: NativeTaskConfig) -> None:
        n = self.num_envs
        # actions
        if not cfg.actions:
            raise ValueError(
                "env.native.actions is empty; add an action term such as DeltaQposTerm"
            )
        self._action_terms = []
        dim = 0
        for key, term in cfg.actions.items():
            t = _as_dict(term)
            cls = ACTIONS.get(t["func"], f"actions.{key}")
            params = plain(t.get("params") or {})
            _check_params(cls, params, f"actions.{key}", skip=2, env=self)
            try:
                inst = cls(self, **params)
            except _TERM_ERRORS as exc:
                raise _named(exc, f"actions.{key}") from exc
            self._action_terms.append((slice(dim, dim + inst.action_dim), inst))
            dim += inst.action_dim
        self.action_dim = dim
        self.action = np.zeros((n, dim))  # the current (clipped) action
        self.prev_action = np.zeros((n, dim))  # the previous step's action
        # events
        self._startup_events, self._reset_events, self._interval_events = [], [], []
        for key, term in (cfg.events or {}).items():
            t = _as_dict(term)
            func = EVENTS.get(t["func"], f"events.{key}")
            mode = _choose(t.get("mode", "reset"), EVENT_MODES, f"events.{key}.mode")
            params = plain(t.get("params") or {})
            _check_params(func, params, f"events.{key}", skip=2, env=self)
            every = t.get("interval_step", 1)
            Number(ge=1, integer=True).check(every, f"events.{key}.interval_step")
            entry = (key, func, params, int(every))
            {
                "startup": self._startup_events,
                "reset": self._reset_events,
                "interval": self._interval_events,
            }[mode].append(entry)
        # observations
        self._observation_terms = []
        for key, term in (cfg.observations or {}).items():
            t = _as_dict(term)
            func = OBSERVATIONS.get(t["func"], f"observations.{key}")
            mode = _choose(t.get("mode", "add"), OBSERVATION_MODES, f"observations.{key}.mode")
            name = t.get("name")
            if not name or name == "???" or name.strip("/") != name or "//" in name:
                raise ValueError(f"observations.{key}.name must be 'group/key', got {name!r}")
            params = plain(t.get("params") or {})
            skip = 2 if mode == "modify" else 1
            _check_params(func, params, f"observations.{key}", skip=skip, env=self)
            self._observation_terms.append((key, func, mode, name, params))
        # rewards
        self._reward_terms = []
        for key, term in (cfg.rewards or {}).items():
            t = _as_dict(term)
            func = REWARDS.get(t["func"], f"rewards.{key}")
            mode = _choose(t.get("mode", "add"), REWARD_MODES, f"rewards.{key}.mode")
            params = plain(t.get("params") or {})
            _check_params(func, params, f"rewards.{key}", skip=1, env=self)
            weight = t.get("weight", 1.0)
            Number().check(weight, f"rewards.{key}.weight")
            self._reward_terms.append((key, func, mode, float(weight), params))
        self.reward_names = [k for k, *_ in self._reward_terms]

    def _make_specs(self) -> None:
        n, dev = self.num_envs, self.device
        self.observation_spec = Composite(
            observation=Unbounded((n, self.obs_dim), dtype=torch.float32, device=dev),
            rewards=Composite(
                {k: Unbounded((n, 1), dtype=torch.float32, device=dev) for k in self.reward_names},
                shape=(n,),
                device=dev,
            ),
            metrics=Composite(
                success=Unbounded((n, 1), dtype=torch.float32, device=dev), shape=(n,), device=dev
            ),
            shape=(n,),
            device=dev,
        )
        self.action_spec = Bounded(-1.0, 1.0, (n, self.action_dim), dtype=torch.float32, device=dev)
        self.reward_spec = Unbounded((n, 1), dtype=torch.float32, device=dev)
        self.done_spec = Composite(
            done=Categorical(2, (n, 1), dtype=torch.bool, device=dev),
            terminated=Categorical(2, (n, 1), dtype=torch.bool, device=dev),
            truncated=Categorical(2, (n, 1), dtype=torch.bool, device=dev),
            shape=(n,),
            device=dev,
        )

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

    # ------------------------------------------------------------------ the MDP

    def _fire(self, events: list, env_ids: np.ndarray) -> None:
        for key, func, params, _ in events:
            try:
                func(self, env_ids, **params)
            except _TERM_ERRORS as exc:
                raise _named(exc, f"events.{key}") from exc

    def _reset_envs(self, env_ids: np.ndarray) -> None:
        """Put envs ``env_ids`` back to their initial state and fire the reset events (batched)."""
        self._state[env_ids] = self._init_state
        self._ctrl[env_ids] = self._init_ctrl
        self.action[env_ids] = 0.0
        self.prev_action[env_ids] = 0.0
        self.episode_step[env_ids] = 0
        self._v.version += 1
        self._fire(self._reset_events, env_ids)

    def _observation_dict(self) -> dict[str, np.ndarray]:
        obs = {
            "robot/qpos": self.robot_qpos(),
            "robot/qvel": self.robot_qvel(),
            "robot/qf": self.robot_qf(),
        }
        for key, func, mode, name, params in self._observation_terms:
            if mode == "modify":
                if name not in obs:
                    raise KeyError(
                        f"observations.{key}: mode 'modify' needs an existing entry {name!r}; have {sorted(obs)}"
                    )
                try:
                    obs[name] = func(self, obs[name], **params)
                except _TERM_ERRORS as exc:
                    raise _named(exc, f"observations.{key}") from exc
            else:
                if name in obs:
                    raise KeyError(
                        f"observations.{key}: mode 'add' but {name!r} already exists; use mode 'modify'"
                    )
                try:
                    obs[name] = func(self, **params)
                except _TERM_ERRORS as exc:
                    raise _named(exc, f"observations.{key}") from exc
        return obs

    def _layout(self, obs: dict[str, np.ndarray]) -> list[tuple[str, int, int, tuple[int, ...]]]:
        """(name, start, stop, shape) of each entry in the flat observation: keys sorted at every level."""
        layout, start = [], 0
        for name in sorted(obs, key=lambda k: tuple(k.split("/"))):
            shape = tuple(obs[name].shape[1:])
            size = int(np.prod(shape))
            layout.append((name, start, start + size, shape))
            start += size
        return layout

    def _flatten(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        out = np.empty((self.num_envs, self.obs_dim), dtype=np.float32)
        for name, start, stop, _ in self.observation_layout:
            out[:, start:stop] = obs[name].reshape(self.num_envs, -1)
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.step_action(tensordict.get("action"))

    def autoreset_observation(self, next_td: TensorDictBase) -> torch.Tensor:
        """The observation to act on after a ``step_action``: the step's own for running envs, the
        fresh reset one for envs that finished (reset inside the step); hands those resets out.
        What rlexp's collector uses instead of a masked ``reset()``."""
        self._pending_reset[:] = False
        return torch.from_numpy(self._v.current_obs.copy())

    def step_action(self, action: torch.Tensor) -> TensorDictBase:
        """One batched step from an action tensor (the body of ``_step``)."""
        n = self.num_envs
        self._pending_reset[:] = False
        if action.device.type != "cpu":
            action = action.cpu()
        self.prev_action[:] = self.action
        np.clip(action.detach().numpy(), -1.0, 1.0, out=self.action)
        if self._interval_events:
            self._v.interval_count += 1
            for key, func, params, every in self._interval_events:
                if self._v.interval_count % every == 0:
                    try:
                        func(self, np.arange(n), **params)
                    except _TERM_ERRORS as exc:
                        raise _named(exc, f"events.{key}") from exc
        for sl, term in self._action_terms:
            term(self, self.action[:, sl], self._ctrl)

        # physics: N envs x substeps in C
        self._control[:] = self._ctrl[:, None, :]
        self._pool.rollout(
            self._models,
            self._datas,
            self._state,
            self._control,
            control_spec=mujoco.mjtState.mjSTATE_CTRL.value,
            skip_checks=True,
            nstep=self.substeps,
            state=self._traj,
            sensordata=self._sensordata,
            chunk_size=self._chunk,
        )
        self._state[:] = self._traj[:, -1]
        self._v.version += 1
        self.episode_step += 1

        task = self.task_spec
        self.success[:] = task.success(self) if task.success else False
        if task.terminated is task.success:  # e.g. PushCube: success ends the episode
            self.terminated[:] = self.success
        else:
            self.terminated[:] = task.terminated(self) if task.terminated else False
        truncated = self.episode_step >= self.max_episode_steps
        if task.truncated:
            truncated |= task.truncated(self)
        np.logical_and(truncated, ~self.terminated, out=self.truncated)

        reward = np.zeros(n)
        terms = {}
        for key, func, mode, weight, params in self._reward_terms:
            value = weight * func(self, **params)
            if mode == "replace":
                reward = value.copy()
            else:
                reward += value
            terms[key] = torch.from_numpy(value.astype(np.float32)[:, None])

        obs = self._flatten(self._observation_dict())  # the true final observation of finished envs
        done = self.terminated | self.truncated
        self._v.current_obs = obs
        if done.any():
            ids = np.flatnonzero(done)
            self._reset_envs(ids)
            self._pending_reset[ids] = True
            fresh = self._flatten(self._observation_dict())
            fresh[~done] = obs[~done]
            self._v.current_obs = fresh

        return self._tensordict(
            {
                "observation": torch.from_numpy(obs),
                "reward": torch.from_numpy(reward.astype(np.float32)[:, None]),
                "done": torch.from_numpy(done[:, None].copy()),
                "terminated": torch.from_numpy(self.terminated[:, None].copy()),
                "truncated": torch.from_numpy(self.truncated[:, None].copy()),
            },
            terms,
            {"success": torch.from_numpy(self.success.astype(np.float32)[:, None])},
        )

    def _tensordict(
        self,
        root: dict[str, torch.Tensor],
        rewards: dict[str, torch.Tensor],
        metrics: dict[str, torch.Tensor],
    ) -> TensorDictBase:
        """The output TensorDict; on CPU built without per-entry validation (the shapes are ours)."""
        bs, dev = self.batch_size, self.device
        if dev.type == "cpu":
            new = TensorDict._new_unsafe
            root["rewards"] = new(rewards, batch_size=bs, device=dev)
            root["metrics"] = new(metrics, batch_size=bs, device=dev)
            return new(root, batch_size=bs, device=dev)
        root["rewards"] = TensorDict(rewards, batch_size=bs, device=dev)
        root["metrics"] = TensorDict(metrics, batch_size=bs, device=dev)
        return TensorDict(root, batch_size=bs, device=dev)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        mask = None
        if tensordict is not None:
            mask = tensordict.get("_reset", None)
        self.last_reset_was_restore = mask is None and self._restored
        if self.last_reset_was_restore:
            # Restored from a checkpoint (load_env_state): the first full reset continues the episodes.
            self._restored = False
            return self.current_tensordict()
        if mask is None:
            ids = np.arange(self.num_envs)
            self._pending_reset[:] = False
        else:
            m = mask.reshape(self.num_envs).cpu().numpy()
            ids = np.flatnonzero(
                m & ~self._pending_reset
            )  # asked for but not already reset in _step
            self._pending_reset[m] = False
        if ids.size:
            self._reset_envs(ids)
            fresh = self._flatten(self._observation_dict())
            keep = np.ones(self.num_envs, dtype=bool)
            keep[ids] = False
            fresh[keep] = self._v.current_obs[keep]
            self._v.current_obs = fresh
        return self.current_tensordict()

    def current_tensordict(self) -> TensorDictBase:
        """The envs' current observation as a reset would return it (e.g. after ``load_state_dict``)."""
        n = self.num_envs
        zeros = torch.zeros((n, 1), dtype=torch.float32)
        false = torch.zeros((n, 1), dtype=torch.bool)
        return self._tensordict(
            {
                "observation": torch.from_numpy(self._v.current_obs.copy()),
                "done": false,
                "terminated": false.clone(),
                "truncated": false.clone(),
            },
            {k: zeros.clone() for k in self.reward_names},
            {"success": zeros.clone()},
        )

    def _set_seed(self, seed: int | None) -> None:
        self.rng = np.random.default_rng(seed)

    # ------------------------------------------------------------------ exact resume

    def state_dict(self, *args: Any, **kwargs: Any) -> dict[str, Any]:  # type: ignore[override]
        """Everything needed to continue bit-identically: physics, controls, counters, targets, RNG."""
        s = self._state
        return {
            "task": self.task_spec.name,
            "num_envs": self.num_envs,
            "time": s[:, 0].copy(),
            "qpos": s[:, self._sl_qpos].copy(),
            "qvel": s[:, self._sl_qvel].copy(),
            "act": s[:, self._sl_act].copy(),
            "physics_state": s.copy(),  # the full mjSTATE_FULLPHYSICS rows (time, qpos, qvel, act, ...)
            "ctrl": self._ctrl.copy(),
            "action": self.action.copy(),
            "prev_action": self.prev_action.copy(),
            "episode_step": self.episode_step.copy(),
            "targets": {k: v.copy() for k, v in self._targets.items()},
            "current_obs": self._v.current_obs.copy(),
            "pending_reset": self._pending_reset.copy(),
            "interval_count": self._v.interval_count,
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state_dict: dict[str, Any], *args: Any, **kwargs: Any) -> None:  # type: ignore[override]
        """Restore a ``state_dict()`` taken from an env of the same task and size."""
        sd = state_dict
        if sd["task"] != self.task_spec.name or int(sd["num_envs"]) != self.num_envs:
            raise ValueError(
                f"env state is for task {sd['task']!r} x {sd['num_envs']} envs; this env is "
                f"{self.task_spec.name!r} x {self.num_envs}"
            )
        self._state[:] = np.asarray(sd["physics_state"])
        self._ctrl[:] = np.asarray(sd["ctrl"])
        self.action[:] = np.asarray(sd["action"])
        self.prev_action[:] = np.asarray(sd["prev_action"])
        self.episode_step[:] = np.asarray(sd["episode_step"])
        self._targets = {k: np.array(v, dtype=float) for k, v in sd["targets"].items()}
        self._v.current_obs = np.array(sd["current_obs"], dtype=np.float32)
        self._pending_reset[:] = np.asarray(sd["pending_reset"])
        self._v.interval_count = int(sd["interval_count"])
        rng = np.random.default_rng()
        rng.bit_generator.state = sd["rng"]
        self.rng = rng
        self._v.version += 1

    def env_state(self) -> dict[str, Any]:
        """The trainer's name for ``state_dict()``: what a checkpoint stores for this env."""
        return self.state_dict()

    def load_env_state(self, state: dict[str, Any]) -> None:
        """Restore a checkpoint's env state; the next full ``reset()`` continues from it (no new episodes)."""
        self.load_state_dict(state)
        self._restored = True

    # ------------------------------------------------------------------ rendering

    def render(
        self,
        env_id: int = 0,
        width: int = 640,
        height: int = 480,
        eye: tuple[float, float, float] | None = None,
        target: tuple[float, float, float] | None = None,
        up: tuple[float, float, float] = (0.0, 0.0, 1.0),
        fovy: float | None = None,
        intrinsics: tuple[float, float, float, float] | None = None,
    ) -> np.ndarray:
        """An RGB frame (H, W, 3) uint8 of env ``env_id`` from a free camera at ``eye`` looking at ``target``.

        ``fovy`` (degrees) or pinhole ``intrinsics`` [fx, fy, cx, cy] (pixels) set the projection;
        neither: the model's default 45 degree field of view.
        """
        from rlexp.envs.native.render import render_frame

        if not 0 <= env_id < self.num_envs:
            raise IndexError(f"env_id {env_id} out of range for {self.num_envs} envs")
        if self._render_data is None:
            self._render_data = mujoco.MjData(self.model)
        d = self._render_data
        mujoco.mj_setState(self.model, d, self._state[env_id], mujoco.mjtState.mjSTATE_FULLPHYSICS)
        d.ctrl[:] = self._ctrl[env_id]
        for body, key in self.task_spec.markers.items():
            if key in self._targets:
                d.mocap_pos[self.model.body(body).mocapid[0]] = self._targets[key][env_id]
        mujoco.mj_forward(self.model, d)
        cam = self.task_spec.camera
        return render_frame(
            self,
            d,
            width,
            height,
            eye=eye if eye is not None else cam.get("eye", (2.0, -2.0, 2.0)),
            target=target if target is not None else cam.get("target", (0.0, 0.0, 0.0)),
            up=up,
            fovy=fovy,
            intrinsics=intrinsics,
        )

    def close(self, *args: Any, **kwargs: Any) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()
        super().close(*args, **kwargs)
