"""Built-in events: domain randomisation, observation / action noise, rollout recording, eval video.

Each is registered under the name a config uses (``func: randomize_physics``) with a rule for every
parameter and the modes and managers where it does something; docs/events.md has the rules table
and the on-disk formats. Every file an event writes stays inside the run dir (``save_path`` is a
folder under it; an absolute folder only with ``allow_outside_run_dir: true``), checked when the
config is validated and again when the file is written (``rlexp.events.output``).

This module is the catalogue: each event's registration, rules and call. How they reach into the
env is ``rlexp.events.env_access``; record_video's checks before the run, ``rlexp.events.video``.
Importing ``rlexp.events`` imports this module, which registers them.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlexp.common.observations import structured, vector_of, with_vector
from rlexp.config.native_task import FileName, Interval, Number, OrNull, Vector
from rlexp.envs.native.events import OBJECT_POSE_PARAMS, TARGET_POSE_PARAMS
from rlexp.events.env_access import (
    base_env,
    env_model,
    event_env_ids,
    native_check_env,
    native_event,
    nominal_model,
    refresh_observation,
)
from rlexp.events.manager import EventContext, register_event
from rlexp.events.output import check_save_path, output_dir, save_params, write_new_file
from rlexp.events.video import VIDEO_DEFAULTS, check_video_env, check_video_params, write_mp4

log = logging.getLogger(__name__)


# field -> (model attribute, columns scaled)
_PHYSICS_FIELDS = {
    "friction": ("geom_friction", [0]),  # sliding friction of every geom
    "mass": ("body_mass", None),
    "damping": ("dof_damping", None),
    "actuator_gain": ("actuator_gainprm", [0]),  # kp of position servos / gear of motors
}


_FACTOR = " (factors of the nominal value; 0 would remove it)"
_RANDOMIZE_MODES = ("startup", "reset", "interval", "trigger")


@register_event(
    "randomize_physics",
    params={
        "friction_range": Interval(gt=0, note=_FACTOR),
        "mass_range": Interval(gt=0, note=_FACTOR),
        "damping_range": Interval(ge=0, note=" (factors of the nominal value)"),
        "actuator_gain_range": Interval(gt=0, note=_FACTOR),
    },
    modes=_RANDOMIZE_MODES,
)
class RandomizePhysics:
    """Per-env domain randomisation of MuJoCo physics: each listed quantity is set to its nominal
    value times a factor drawn uniformly from its range, independently per env and element.

    params: ``friction_range``, ``mass_range``, ``damping_range``, ``actuator_gain_range`` (each
    ``[low, high]`` factors; omit to leave a quantity alone, give at least one). Position servos
    keep their stiffness consistent: scaling ``actuator_gain`` also scales their ``biasprm[1]`` (-kp).
    """

    def __init__(self) -> None:
        self.factors: dict[str, np.ndarray] = {}  # field -> [num_envs, size] factors in effect
        self.nominal: dict[str, np.ndarray] = {}

    @staticmethod
    def check_params(params: dict[str, Any], where: str) -> None:
        if not params:
            raise ValueError(
                f"{where}.params is empty: randomize_physics needs at least one of "
                f"{[f + '_range' for f in _PHYSICS_FIELDS]}"
            )

    @staticmethod
    def check_env(env: Any, where: str, num_envs: int | None = None, **ranges: Any) -> None:
        """The env exposes MuJoCo models with the quantities to randomise."""
        base = base_env(env)
        try:
            model = nominal_model(base)
        except (TypeError, AttributeError, IndexError) as exc:
            raise TypeError(f"{where}: randomize_physics needs a MuJoCo env: {exc}") from None
        for key in ranges:
            attr, _ = _PHYSICS_FIELDS[key.removesuffix("_range")]
            if np.asarray(getattr(model, attr)).size == 0:
                raise ValueError(f"{where}.params.{key}: the env's model has no {attr} to scale")

    def __call__(self, ctx: EventContext, **ranges: Any) -> None:
        env = base_env(ctx.env)
        ids = event_env_ids(ctx)
        n = int(env.batch_size.numel())
        for key, rng_range in ranges.items():
            field = key.removesuffix("_range")
            attr, cols = _PHYSICS_FIELDS[field]
            nominal = self._nominal(env, field, attr, cols)
            if field not in self.factors:
                self.factors[field] = np.ones((n, nominal.size))
            low, high = float(rng_range[0]), float(rng_range[1])
            self.factors[field][ids] = ctx.rng.uniform(low, high, size=(len(ids), nominal.size))
            self._apply(env, field, ids)

    def _nominal(self, env: Any, field: str, attr: str, cols: list[int] | None) -> np.ndarray:
        if field not in self.nominal:
            values = np.array(getattr(nominal_model(env), attr), dtype=float)
            self.nominal[field] = values[:, cols].reshape(-1) if cols else values.reshape(-1)
            if field == "actuator_gain":
                self.nominal["actuator_bias"] = np.array(
                    nominal_model(env).actuator_biasprm[:, 1], dtype=float
                )
        return self.nominal[field]

    def _apply(self, env: Any, field: str, ids: np.ndarray) -> None:
        attr, cols = _PHYSICS_FIELDS[field]
        for i in ids:
            model = env_model(env, int(i), private=True)
            values = self.nominal[field] * self.factors[field][i]
            target = getattr(model, attr)
            if cols:
                target[:, cols[0]] = values
            else:
                target[:] = values
            if field == "actuator_gain":
                model.actuator_biasprm[:, 1] = (
                    self.nominal["actuator_bias"] * self.factors[field][i]
                )

    def state_dict(self) -> dict[str, Any]:
        return {
            "factors": {k: torch.from_numpy(v.copy()) for k, v in self.factors.items()},
            "nominal": {k: torch.from_numpy(v.copy()) for k, v in self.nominal.items()},
        }

    def load_state_dict(self, sd: dict[str, Any], env: Any = None) -> None:
        self.factors = {k: np.asarray(v, dtype=float) for k, v in sd["factors"].items()}
        self.nominal = {k: np.asarray(v, dtype=float) for k, v in sd["nominal"].items()}
        if env is not None:
            base = base_env(env)
            for field in self.factors:
                self._apply(base, field, np.arange(self.factors[field].shape[0]))


@register_event(
    "randomize_object_pose",
    params=OBJECT_POSE_PARAMS,
    required=("entity_cfg", "position_range"),
    modes=_RANDOMIZE_MODES,
)
def randomize_object_pose(ctx: EventContext, **params: Any) -> None:
    """Native tasks: move a rigid object (``entity_cfg.uid``) within ``position_range`` per env;
    same parameters as the task-file event ``randomize_rigid_object_pose``."""
    env = base_env(ctx.env)
    native_event("randomize_rigid_object_pose")(env, event_env_ids(ctx), **params)
    refresh_observation(env)


randomize_object_pose.check_env = native_check_env("randomize_rigid_object_pose")  # type: ignore[attr-defined]


@register_event(
    "randomize_goal_pose",
    params=TARGET_POSE_PARAMS,
    required=("position_range",),
    modes=_RANDOMIZE_MODES,
)
def randomize_goal_pose(ctx: EventContext, **params: Any) -> None:
    """Native tasks: redraw the goal within ``position_range`` per env (as ``randomize_target_pose``)."""
    env = base_env(ctx.env)
    native_event("randomize_target_pose")(env, event_env_ids(ctx), **params)
    refresh_observation(env)


randomize_goal_pose.check_env = native_check_env("randomize_target_pose")  # type: ignore[attr-defined]


@register_event(
    "observation_noise",
    params={
        "std": Number(ge=0, note=" (standard deviation, in observation units)"),
        "clip": OrNull(Number(gt=0), "no clipping"),
    },
    modes=("step",),
    managers=("train",),  # evaluation fires step events before the env step only
)
def observation_noise(ctx: EventContext, std: float = 0.01, clip: float | None = None) -> None:
    """Step event: add N(0, std^2) to the observations the policy sees (and that are stored):
    the flat vector (with images, the observation's ``vector`` entry; images are left as they are)."""
    if ctx.phase != "observation" or ctx.tensordict is None:
        return
    full = ctx.tensordict.get("observation")
    obs = vector_of(full)
    if obs is None:  # images only: nothing to add noise to
        return
    noise = torch.from_numpy(ctx.rng.normal(0.0, std, size=tuple(obs.shape)).astype(np.float32))
    if clip is not None:
        noise.clamp_(-clip, clip)
    ctx.tensordict.set("observation", with_vector(full, obs + noise.to(obs.device)))


@register_event(
    "action_noise",
    params={"std": Number(ge=0, note=" (standard deviation, in action units)")},
    modes=("step",),
)
def action_noise(ctx: EventContext, std: float = 0.05) -> None:
    """Step event: the env executes the policy's action plus N(0, std^2); the stored action (and its
    log-probability) stay the policy's own, so PPO's ratio is unbiased."""
    if ctx.phase != "action" or ctx.tensordict is None:
        return
    act = ctx.tensordict.get("action")
    noise = torch.from_numpy(ctx.rng.normal(0.0, std, size=tuple(act.shape)).astype(np.float32))
    ctx.tensordict.set("action", act + noise.to(act.device))


def _check_continuous_actions(env: Any, where: str, num_envs: int | None = None, **_: Any) -> None:
    """Gaussian noise on an action needs continuous (Box) actions."""
    if getattr(env.action_spec, "domain", "continuous") == "discrete":
        name = getattr(base_env(env), "env_id", type(base_env(env)).__name__)
        raise TypeError(
            f"{where}: action_noise adds Gaussian noise to continuous (Box) actions; "
            f"env.name={name!r} has discrete actions (observation_noise and record_rollouts work)"
        )


action_noise.check_env = _check_continuous_actions  # type: ignore[attr-defined]


@register_event(
    "record_rollouts",
    params=save_params("rollouts"),
    modes=("interval",),
    managers=("train",),  # the collected batch exists only there
)
def record_rollouts(
    ctx: EventContext, save_path: str | None = None, allow_outside_run_dir: bool = False
) -> None:
    """Interval event (training): write the rollout just collected to ``rollouts/step_<N>.npz``.

    Arrays, all ``[num_envs, T, ...]``: ``observation``, ``action``, ``reward``, ``done``,
    ``terminated``, ``truncated``, ``next_observation``; plus ``global_step`` (scalar). With image
    observations (a TensorDict) each entry is an array of its own, in its own dtype (images uint8):
    ``observation.vector``, ``observation.<image key>``, ``next_observation.<...>``.
    """
    if ctx.batch is None:
        return
    out_dir = output_dir(ctx, save_path, "rollouts", allow_outside_run_dir)
    b = ctx.batch
    arrays = {
        **_observation_arrays("observation", b["observation"]),
        "action": b["action"],
        "reward": b["next", "reward"].squeeze(-1),
        "done": b["next", "done"].squeeze(-1),
        "terminated": b["next", "terminated"].squeeze(-1),
        "truncated": b["next", "truncated"].squeeze(-1),
        **_observation_arrays("next_observation", b["next", "observation"]),
    }
    data = {k: v.detach().cpu().numpy() for k, v in arrays.items()}

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, global_step=np.int64(ctx.global_step), **data)

    write_new_file(out_dir / f"step_{ctx.global_step:09d}.npz", write)


record_rollouts.check_params = check_save_path  # type: ignore[attr-defined]


def _observation_arrays(name: str, obs: Any) -> dict[str, torch.Tensor]:
    """``{name: obs}``, or per entry of a TensorDict observation ``{name.<key>: entry}``."""
    if not structured(obs):
        return {name: obs}
    return {f"{name}.{key}": obs.get(key) for key in sorted(obs.keys())}


@register_event(
    "record_video",
    params={
        "name": FileName(),
        "resolution": Vector(names=("width", "height"), ge=1, integer=True, note="pixels"),
        "eye": OrNull(Vector(note="m"), "the task's camera position"),
        "target": OrNull(Vector(note="m"), "the task's camera target"),
        "up": Vector(note="not parallel to target - eye"),
        "intrinsics": OrNull(
            Vector(names=("fx", "fy", "cx", "cy"), gt=0, bounded=("fx", "fy"), note="pixels"),
            "fovy, else 45 degrees",
        ),
        "fovy": OrNull(Number(gt=0, lt=180, note=" (degrees)"), "intrinsics, else 45 degrees"),
        "env_id": Number(ge=0, integer=True, note=" (< env.num_eval_envs)"),
        "max_frames": Number(ge=1, integer=True, note=" (frames kept per round)"),
        "fps": Number(gt=0),
        **save_params("videos"),
    },
    modes=("interval", "step"),
    managers=("eval",),  # the video is written when an evaluation round ends
)
class RecordVideo:
    """Evaluation video: renders env ``env_id`` of the eval env at every call (an eval step) and writes
    an mp4 when the round ends (``finalize``).

    params: ``name``, ``resolution`` [width, height], ``eye``, ``target``, ``up``, ``intrinsics``
    [fx, fy, cx, cy] (or ``fovy``), ``save_path`` (a folder under the run dir; default ``videos``),
    ``allow_outside_run_dir``, ``fps``, ``env_id``, ``max_frames``. File:
    ``<run_dir>/<save_path>/<name>_step_<global_step>.mp4``. ``check_env`` renders one frame before
    the run starts.
    """

    DEFAULTS: dict[str, Any] = VIDEO_DEFAULTS
    check_params = staticmethod(check_video_params)
    check_env = staticmethod(check_video_env)

    def __init__(self) -> None:
        self.frames: list[np.ndarray] = []
        self.written: list[Path] = []
        self.failed: str | None = None  # why the last video could not be written

    def __call__(
        self,
        ctx: EventContext,
        *,
        resolution=(640, 480),
        eye=None,
        target=None,
        up=(0, 0, 1),
        intrinsics=None,
        fovy=None,
        env_id: int = 0,
        max_frames: int = 2000,
        **_: Any,
    ) -> None:
        if len(self.frames) >= max_frames:
            return
        env = base_env(ctx.env)
        frame = env.render(
            env_id=env_id,
            width=int(resolution[0]),
            height=int(resolution[1]),
            eye=eye,
            target=target,
            up=up,
            intrinsics=intrinsics,
            fovy=fovy,
        )
        self.frames.append(np.asarray(frame, dtype=np.uint8))

    def finalize(
        self,
        ctx: EventContext,
        *,
        name: str = "eval",
        save_path: str | None = None,
        allow_outside_run_dir: bool = False,
        fps: float = 25,
        **_: Any,
    ) -> None:
        if not self.frames:
            return
        FileName().check(name, f"{ctx.event or 'record_video'}.params.name")
        out_dir = output_dir(ctx, save_path, "videos", allow_outside_run_dir)
        path = out_dir / f"{name}_step_{ctx.global_step:09d}.mp4"
        frames, self.frames = self.frames, []
        self.failed = None
        try:
            write_mp4(path, frames, fps)
        except OSError as exc:  # a full disk: this video is lost, the run goes on
            self.failed = f"{path}: {exc.strerror or exc}"
            log.warning("[video] not written (%d frames): %s", len(frames), self.failed)
            return
        log.info("[video] %s (%d frames)", path, len(frames))
        self.written.append(path)
