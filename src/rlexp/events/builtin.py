"""Built-in events: domain randomisation, observation / action noise, rollout recording, eval video.

Each is registered under the name a config uses (``func: randomize_physics``) with a rule for every
parameter and the modes and managers where it does something; docs/events.md has the rules table
and the on-disk formats. Every file an event writes stays inside the run dir (``save_path`` is a
folder under it; an absolute folder only with ``allow_outside_run_dir: true``), checked when the
config is validated and again when the file is written.
"""

from __future__ import annotations

import copy
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlexp.config.native_task import (
    FileName,
    Flag,
    Interval,
    Number,
    OrNull,
    SavePath,
    Vector,
    check_params,
)
from rlexp.envs.native.events import OBJECT_POSE_PARAMS, TARGET_POSE_PARAMS
from rlexp.events.manager import EventContext, register_event

log = logging.getLogger(__name__)


def _ids(ctx: EventContext) -> np.ndarray:
    n = int(ctx.env.batch_size.numel())
    return (
        np.arange(n) if ctx.env_ids is None else np.asarray(ctx.env_ids, dtype=np.int64).reshape(-1)
    )


def _base_env(env: Any) -> Any:
    """The env under TorchRL transforms."""
    while hasattr(env, "base_env"):
        env = env.base_env
    return env


def _env_model(env: Any, i: int, private: bool):
    """Env ``i``'s MuJoCo model; ``private``: give a batched native env its own copy first."""
    if hasattr(env, "_models"):  # native batched env: one model per env in its rollout list
        if private and env._models[i] is env.model:
            env._models[i] = copy.copy(env.model)
        return env._models[i]
    if hasattr(env, "_envs"):  # GymnasiumEnv: each copy owns its model
        return env._envs[i].unwrapped.model
    raise TypeError(f"{type(env).__name__} exposes no MuJoCo models to randomise")


def _nominal_model(env: Any):
    if hasattr(env, "_models"):
        return env.model
    model = getattr(getattr(env, "_envs", [None])[0], "unwrapped", None)
    model = getattr(model, "model", None)
    if model is None:
        raise TypeError(f"{type(env).__name__} exposes no MuJoCo models to randomise")
    return model


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
        base = _base_env(env)
        try:
            model = _nominal_model(base)
        except (TypeError, AttributeError, IndexError) as exc:
            raise TypeError(f"{where}: randomize_physics needs a MuJoCo env: {exc}") from None
        for key in ranges:
            attr, _ = _PHYSICS_FIELDS[key.removesuffix("_range")]
            if np.asarray(getattr(model, attr)).size == 0:
                raise ValueError(f"{where}.params.{key}: the env's model has no {attr} to scale")

    def __call__(self, ctx: EventContext, **ranges: Any) -> None:
        env = _base_env(ctx.env)
        ids = _ids(ctx)
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
            values = np.array(getattr(_nominal_model(env), attr), dtype=float)
            self.nominal[field] = values[:, cols].reshape(-1) if cols else values.reshape(-1)
            if field == "actuator_gain":
                self.nominal["actuator_bias"] = np.array(
                    _nominal_model(env).actuator_biasprm[:, 1], dtype=float
                )
        return self.nominal[field]

    def _apply(self, env: Any, field: str, ids: np.ndarray) -> None:
        attr, cols = _PHYSICS_FIELDS[field]
        for i in ids:
            model = _env_model(env, int(i), private=True)
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
            base = _base_env(env)
            for field in self.factors:
                self._apply(base, field, np.arange(self.factors[field].shape[0]))


def _native_event(name: str):
    from rlexp.envs.native import EVENTS

    return EVENTS.get(name)


def _native_check_env(native_name: str) -> Callable[..., None]:
    """``check_env`` of a built-in event that runs the native task event ``native_name``: the env
    is a native task and the params name its objects."""

    def check_env(env: Any, where: str, num_envs: int | None = None, **params: Any) -> None:
        base = _base_env(env)
        if not hasattr(base, "object_pose"):
            raise TypeError(
                f"{where}: {native_name} moves objects of the native tasks (env=push_cube); "
                f"this env is {type(base).__name__}"
            )
        func = _native_event(native_name)
        check_params(native_name, params, func.PARAMS, f"{where}.params", env=base)

    return check_env


@register_event(
    "randomize_object_pose",
    params=OBJECT_POSE_PARAMS,
    required=("entity_cfg", "position_range"),
    modes=_RANDOMIZE_MODES,
)
def randomize_object_pose(ctx: EventContext, **params: Any) -> None:
    """Native tasks: move a rigid object (``entity_cfg.uid``) within ``position_range`` per env;
    same parameters as the task-file event ``randomize_rigid_object_pose``."""
    env = _base_env(ctx.env)
    _native_event("randomize_rigid_object_pose")(env, _ids(ctx), **params)
    _refresh(env)


randomize_object_pose.check_env = _native_check_env("randomize_rigid_object_pose")  # type: ignore[attr-defined]


@register_event(
    "randomize_goal_pose",
    params=TARGET_POSE_PARAMS,
    required=("position_range",),
    modes=_RANDOMIZE_MODES,
)
def randomize_goal_pose(ctx: EventContext, **params: Any) -> None:
    """Native tasks: redraw the goal within ``position_range`` per env (as ``randomize_target_pose``)."""
    env = _base_env(ctx.env)
    _native_event("randomize_target_pose")(env, _ids(ctx), **params)
    _refresh(env)


randomize_goal_pose.check_env = _native_check_env("randomize_target_pose")  # type: ignore[attr-defined]


def _refresh(env: Any) -> None:
    """Recompute a native env's current observation after its state was changed from outside."""
    if hasattr(env, "_observation_dict"):
        env._v.current_obs = env._flatten(env._observation_dict())


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
    """Step event: add N(0, std^2) to the observations the policy sees (and that are stored)."""
    if ctx.phase != "observation" or ctx.tensordict is None:
        return
    obs = ctx.tensordict.get("observation")
    noise = torch.from_numpy(ctx.rng.normal(0.0, std, size=tuple(obs.shape)).astype(np.float32))
    if clip is not None:
        noise.clamp_(-clip, clip)
    ctx.tensordict.set("observation", obs + noise.to(obs.device))


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


def _save_params(default: str) -> dict[str, Any]:
    return {
        "save_path": OrNull(SavePath(), f"{default}/ in the run dir"),
        "allow_outside_run_dir": Flag(),
    }


def _check_save_path(params: dict[str, Any], where: str) -> None:
    """An absolute ``save_path`` writes outside the run dir: only with an explicit opt-in, and the
    opt-in needs the absolute folder it is for."""
    save_path, allow = params.get("save_path"), params.get("allow_outside_run_dir", False)
    absolute = save_path is not None and os.path.isabs(save_path)
    if absolute and not allow:
        raise ValueError(
            f"{where}.params.save_path={save_path!r} is outside the run dir; give a folder relative "
            f"to the run dir (e.g. 'videos'), or set {where}.params.allow_outside_run_dir=true to "
            "write there on purpose"
        )
    if allow and not absolute:
        raise ValueError(
            f"{where}.params.allow_outside_run_dir=true needs an absolute save_path (the folder "
            f"outside the run dir); got save_path={save_path!r}"
        )


def output_dir(
    ctx: EventContext, save_path: str | None, default: str, allow_outside_run_dir: bool = False
) -> Path:
    """The folder an event writes into, created: ``<run_dir>/<save_path or default>``, which must
    still be inside the run dir once ``..`` and symlinks are resolved; an absolute ``save_path``
    only with ``allow_outside_run_dir``."""
    event = ctx.event or "event"
    if save_path is not None and os.path.isabs(save_path):
        if not allow_outside_run_dir:
            raise ValueError(
                f"{event}.params.save_path={save_path!r} is outside the run dir "
                "(allow_outside_run_dir is not set)"
            )
        out = Path(save_path)
        out.mkdir(parents=True, exist_ok=True)
        return out
    if ctx.run_dir is None:
        raise ValueError(f"{event}: no run dir to write into")
    root = Path(ctx.run_dir).resolve()
    out = root / (save_path or default)
    for _ in range(2):  # before creating it, and after (a part created meanwhile may be a link)
        real = out.resolve()
        if real != root and root not in real.parents:
            raise ValueError(
                f"{event}.params.save_path={save_path or default!r} resolves to {real}, outside "
                f"the run dir {root} (a symlink?); nothing was written"
            )
        out.mkdir(parents=True, exist_ok=True)
    return out


def write_new_file(path: Path, write: Callable[[Path], None]) -> None:
    """Write ``path`` through a temporary file created in its folder (never an existing file or
    link) and renamed over it: a link at ``path`` is replaced, not followed, and a killed run
    leaves no half-written file under the final name."""
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    tmp.unlink(missing_ok=True)
    os.close(
        os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
    )
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@register_event(
    "record_rollouts",
    params=_save_params("rollouts"),
    modes=("interval",),
    managers=("train",),  # the collected batch exists only there
)
def record_rollouts(
    ctx: EventContext, save_path: str | None = None, allow_outside_run_dir: bool = False
) -> None:
    """Interval event (training): write the rollout just collected to ``rollouts/step_<N>.npz``.

    Arrays, all ``[num_envs, T, ...]``: ``observation``, ``action``, ``reward``, ``done``,
    ``terminated``, ``truncated``, ``next_observation``; plus ``global_step`` (scalar).
    """
    if ctx.batch is None:
        return
    out_dir = output_dir(ctx, save_path, "rollouts", allow_outside_run_dir)
    b = ctx.batch
    arrays = {
        "observation": b["observation"],
        "action": b["action"],
        "reward": b["next", "reward"].squeeze(-1),
        "done": b["next", "done"].squeeze(-1),
        "terminated": b["next", "terminated"].squeeze(-1),
        "truncated": b["next", "truncated"].squeeze(-1),
        "next_observation": b["next", "observation"],
    }
    data = {k: v.detach().cpu().numpy() for k, v in arrays.items()}

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, global_step=np.int64(ctx.global_step), **data)

    write_new_file(out_dir / f"step_{ctx.global_step:09d}.npz", write)


record_rollouts.check_params = _check_save_path  # type: ignore[attr-defined]


#: Frames are held in memory until the round ends: at most this many bytes of them.
MAX_VIDEO_BYTES = 4 * 2**30


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
        **_save_params("videos"),
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

    DEFAULTS: dict[str, Any] = {
        "name": "eval",
        "resolution": (640, 480),
        "eye": None,
        "target": None,
        "up": (0, 0, 1),
        "intrinsics": None,
        "fovy": None,
        "env_id": 0,
        "max_frames": 2000,
        "fps": 25,
    }

    def __init__(self) -> None:
        self.frames: list[np.ndarray] = []
        self.written: list[Path] = []

    @staticmethod
    def check_params(params: dict[str, Any], where: str) -> None:
        """Rules across parameters, and whether this process can render offscreen at all."""
        from rlexp.envs.native.render import GL_FIX, gl_problem

        _check_save_path(params, where)
        p = {**RecordVideo.DEFAULTS, **params}
        if p["intrinsics"] is not None and p["fovy"] is not None:
            raise ValueError(f"{where}.params: give intrinsics or fovy, not both")
        if p["eye"] is not None and p["target"] is not None:
            forward = np.subtract(p["target"], p["eye"], dtype=float)
            dist = float(np.linalg.norm(forward))
            if dist < 1e-9:
                raise ValueError(f"{where}.params: eye={p['eye']} and target are the same point")
            if np.linalg.norm(np.cross(forward / dist, np.asarray(p["up"], float))) < 1e-9:
                raise ValueError(f"{where}.params.up={p['up']} is parallel to target - eye")
        if np.linalg.norm(np.asarray(p["up"], float)) < 1e-9:
            raise ValueError(f"{where}.params.up={p['up']} must not be zero")
        width, height = (int(v) for v in p["resolution"])
        size = int(p["max_frames"]) * width * height * 3
        if size > MAX_VIDEO_BYTES:
            raise ValueError(
                f"{where}.params: max_frames={p['max_frames']} frames of {width}x{height} hold "
                f"{size / 2**30:.1f} GiB in memory (at most {MAX_VIDEO_BYTES // 2**30} GiB); lower "
                "max_frames or resolution"
            )
        # Only a MUJOCO_GL that MuJoCo refuses to import with (no MuJoCo env could run): whether
        # this machine can render is check_env's question, not the config's (rlexp eval reads the
        # config of a run with videos on machines that cannot render).
        problem = gl_problem(rendering=False)
        if problem is not None:
            raise ValueError(
                f"{where}: cannot render {width}x{height} offscreen: {problem}; {GL_FIX}"
            )

    @classmethod
    def check_env(cls, env: Any, where: str, num_envs: int | None = None, **params: Any) -> None:
        """Render one frame from ``env`` (a throwaway built copy of the eval env: it is reset, as an
        evaluation round does first) with these params, and find the mp4 encoder: what would
        otherwise fail at the end of the first evaluation round."""
        from rlexp.envs.native.render import GL_FIX, gl_problem

        p = {**cls.DEFAULTS, **params}
        if num_envs is not None and p["env_id"] >= num_envs:
            raise ValueError(
                f"{where}.params.env_id={p['env_id']} but the eval env has {num_envs} copies "
                "(env.num_eval_envs)"
            )
        width, height = (int(v) for v in p["resolution"])
        problem = gl_problem()
        if problem is not None:
            raise ValueError(
                f"{where}: cannot render {width}x{height} offscreen: {problem}; {GL_FIX}"
            )
        base = _base_env(env)
        if not hasattr(base, "render"):
            raise TypeError(f"{where}: {type(base).__name__} cannot render frames")
        try:
            base.reset()
            frame = base.render(
                env_id=0,
                width=width,
                height=height,
                eye=p["eye"],
                target=p["target"],
                up=p["up"],
                intrinsics=p["intrinsics"],
                fovy=p["fovy"],
            )
        except Exception as exc:  # GL failures come as RuntimeError, FatalError, AttributeError...
            text = str(exc.args[0] if isinstance(exc, KeyError) and exc.args else exc).strip()
            text = (text.splitlines() or [type(exc).__name__])[0].removeprefix("render: ")
            raise ValueError(f"{where}: cannot render {width}x{height} offscreen: {text}") from None
        frame = np.asarray(frame)
        if frame.ndim != 3 or frame.shape[-1] != 3:
            raise ValueError(
                f"{where}: the env renders frames of shape {frame.shape}, not (H, W, 3)"
            )
        if frame.shape[:2] != (height, width):
            log.warning(
                "%s: the env renders %dx%d frames with its own camera (Gymnasium: env.kwargs.width / "
                "height); resolution and the camera params apply to the native tasks",
                where, frame.shape[1], frame.shape[0],
            )  # fmt: skip
        try:
            import imageio.v2  # noqa: F401
            import imageio_ffmpeg

            imageio_ffmpeg.get_ffmpeg_exe()
        except Exception as exc:  # ImportError, or RuntimeError when no ffmpeg binary is found
            raise ValueError(f"{where}: cannot write mp4 videos: {exc}") from None

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
        env = _base_env(ctx.env)
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
        import imageio.v2 as imageio

        FileName().check(name, f"{ctx.event or 'record_video'}.params.name")
        out_dir = output_dir(ctx, save_path, "videos", allow_outside_run_dir)
        path = out_dir / f"{name}_step_{ctx.global_step:09d}.mp4"
        frames, self.frames = self.frames, []

        def write(tmp: Path) -> None:
            with imageio.get_writer(tmp, fps=fps, codec="libx264", macro_block_size=1) as writer:
                for frame in frames:
                    writer.append_data(frame)

        write_new_file(path, write)
        log.info("[video] %s (%d frames)", path, len(frames))
        self.written.append(path)
