"""Built-in events: domain randomisation, observation / action noise, rollout recording, eval video.

Each is registered under the name a config uses (``func: randomize_physics``). See docs/events.md
for the parameters and the on-disk formats.
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

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
    return env._envs[0].unwrapped.model


# field -> (model attribute, columns scaled)
_PHYSICS_FIELDS = {
    "friction": ("geom_friction", [0]),  # sliding friction of every geom
    "mass": ("body_mass", None),
    "damping": ("dof_damping", None),
    "actuator_gain": ("actuator_gainprm", [0]),  # kp of position servos / gear of motors
}


@register_event("randomize_physics")
class RandomizePhysics:
    """Per-env domain randomisation of MuJoCo physics: each listed quantity is set to its nominal
    value times a factor drawn uniformly from its range, independently per env and element.

    params: ``friction_range``, ``mass_range``, ``damping_range``, ``actuator_gain_range`` (each
    ``[low, high]`` factors; omit to leave a quantity alone). Position servos keep their stiffness
    consistent: scaling ``actuator_gain`` also scales their ``biasprm[1]`` (-kp).
    """

    def __init__(self) -> None:
        self.factors: dict[str, np.ndarray] = {}  # field -> [num_envs, size] factors in effect
        self.nominal: dict[str, np.ndarray] = {}

    def __call__(self, ctx: EventContext, **ranges: Any) -> None:
        env = _base_env(ctx.env)
        ids = _ids(ctx)
        n = int(env.batch_size.numel())
        for key, rng_range in ranges.items():
            field = key.removesuffix("_range")
            if field not in _PHYSICS_FIELDS:
                raise ValueError(
                    f"randomize_physics: unknown parameter {key!r}; choose from "
                    f"{[f + '_range' for f in _PHYSICS_FIELDS]}"
                )
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


@register_event("randomize_object_pose")
def randomize_object_pose(ctx: EventContext, **params: Any) -> None:
    """Native tasks: move a rigid object (``entity_cfg.uid``) within ``position_range`` per env;
    same parameters as the task-file event ``randomize_rigid_object_pose``."""
    env = _base_env(ctx.env)
    _native_event("randomize_rigid_object_pose")(env, _ids(ctx), **params)
    _refresh(env)


@register_event("randomize_goal_pose")
def randomize_goal_pose(ctx: EventContext, **params: Any) -> None:
    """Native tasks: redraw the goal within ``position_range`` per env (as ``randomize_target_pose``)."""
    env = _base_env(ctx.env)
    _native_event("randomize_target_pose")(env, _ids(ctx), **params)
    _refresh(env)


def _refresh(env: Any) -> None:
    """Recompute a native env's current observation after its state was changed from outside."""
    if hasattr(env, "_observation_dict"):
        env._v.current_obs = env._flatten(env._observation_dict())


@register_event("observation_noise")
def observation_noise(ctx: EventContext, std: float = 0.01, clip: float | None = None) -> None:
    """Step event: add N(0, std^2) to the observations the policy sees (and that are stored)."""
    if ctx.phase != "observation" or ctx.tensordict is None:
        return
    obs = ctx.tensordict.get("observation")
    noise = torch.from_numpy(ctx.rng.normal(0.0, std, size=tuple(obs.shape)).astype(np.float32))
    if clip is not None:
        noise.clamp_(-clip, clip)
    ctx.tensordict.set("observation", obs + noise.to(obs.device))


@register_event("action_noise")
def action_noise(ctx: EventContext, std: float = 0.05) -> None:
    """Step event: the env executes the policy's action plus N(0, std^2); the stored action (and its
    log-probability) stay the policy's own, so PPO's ratio is unbiased."""
    if ctx.phase != "action" or ctx.tensordict is None:
        return
    act = ctx.tensordict.get("action")
    noise = torch.from_numpy(ctx.rng.normal(0.0, std, size=tuple(act.shape)).astype(np.float32))
    ctx.tensordict.set("action", act + noise.to(act.device))


@register_event("record_rollouts")
def record_rollouts(ctx: EventContext, save_path: str | None = None, every: int = 1) -> None:
    """Interval event (training): write the rollout just collected to ``rollouts/step_<N>.npz``.

    Arrays, all ``[num_envs, T, ...]``: ``observation``, ``action``, ``reward``, ``done``,
    ``terminated``, ``truncated``, ``next_observation``; plus ``global_step`` (scalar).
    """
    if ctx.batch is None:
        return
    out_dir = Path(save_path) if save_path else (ctx.run_dir or Path(".")) / "rollouts"
    out_dir.mkdir(parents=True, exist_ok=True)
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
    path = out_dir / f"step_{ctx.global_step:09d}.npz"
    np.savez_compressed(
        path,
        global_step=np.int64(ctx.global_step),
        **{k: v.detach().cpu().numpy() for k, v in arrays.items()},
    )


@register_event("record_video")
class RecordVideo:
    """Evaluation video: renders env ``env_id`` of the eval env at every call (an eval step) and writes
    an mp4 when the round ends (``finalize``).

    params: ``name``, ``resolution`` [width, height], ``eye``, ``target``, ``up``, ``intrinsics``
    [fx, fy, cx, cy] (or ``fovy``), ``save_path`` (a folder; default ``<run_dir>/videos``), ``fps``,
    ``env_id``, ``max_frames``. File: ``<save_path>/<name>_step_<global_step>.mp4``.
    """

    def __init__(self) -> None:
        self.frames: list[np.ndarray] = []
        self.written: list[Path] = []

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
        fps: int = 25,
        **_: Any,
    ) -> None:
        if not self.frames:
            return
        import imageio.v2 as imageio

        out_dir = Path(save_path) if save_path else (ctx.run_dir or Path(".")) / "videos"
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / f"{name}_step_{ctx.global_step:09d}.mp4"
        with imageio.get_writer(path, fps=fps, codec="libx264", macro_block_size=1) as writer:
            for frame in self.frames:
                writer.append_data(frame)
        log.info("[video] %s (%d frames)", path, len(self.frames))
        self.written.append(path)
        self.frames = []
