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

import logging
import os
from typing import Any

import mujoco
import numpy as np
import torch
from mujoco import rollout
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from rlexp.config.native_task import NativeTaskConfig, plain
from rlexp.envs.native.obs_table import ROBOT_OBSERVATIONS, make_table, observe
from rlexp.envs.native.scene import load_model
from rlexp.envs.native.state import SimState
from rlexp.envs.native.tasks import TaskSpec, get_task
from rlexp.envs.native.terms import (
    TERM_ERRORS,
    as_dict,
    build_action_terms,
    build_event_terms,
    build_observation_terms,
    build_reward_terms,
    named_error,
)

log = logging.getLogger(__name__)

__all__ = ["ROBOT_OBSERVATIONS", "NativeEnv", "default_num_threads"]


def default_num_threads(num_envs: int) -> int:
    """Physics threads: none (the calling thread) for a few envs, else one per core, at most 16."""
    cores = (
        len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    )
    return 0 if num_envs < 4 or cores < 2 else min(cores, 16, num_envs)


class NativeEnv(EnvBase, SimState):
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
            else NativeTaskConfig(**as_dict(task_cfg))
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
        self._setup_state()
        self._setup_physics(num_threads)
        self._setup_terms(cfg)

        # Build-time pass with a throwaway generator: gives every env a valid state and the targets
        # the observation terms read, and fixes the observation layout. set_seed()/reset() follow.
        # Every startup / reset event, observation and reward runs once here, so a parameter that
        # only fails when used (a target no event stores) fails now, naming the term.
        self.rng = np.random.default_rng(0)
        self._fire(self._startup_events, np.arange(num_envs))
        self._reset_envs(np.arange(num_envs))
        obs, groups = observe(self, self._observation_terms)
        for key, func, _, _, params in self._reward_terms:
            try:
                func(self, **params)
            except TERM_ERRORS as exc:
                raise named_error(exc, f"rewards.{key}") from exc
        self._table = make_table(obs, groups)  # the vector's entries (policy group first), images
        #: (name, start, stop, shape) of each vector entry; ``obs_layout``: every part, its group
        self.observation_layout = list(self._table.entries)
        self.obs_layout = self._table.layout
        self.obs_dim = self._table.dim
        self._v.current_obs = self._table.flatten(obs, num_envs)
        self._v.current_images = self._table.pixels(obs)
        self._make_specs()
        log.info(
            "native env %s: %d envs, obs %d, action %d, %d physics steps/action, %d physics threads",
            self.task_spec.name, num_envs, self.obs_dim, self.action_dim, self.substeps, self.num_threads,
        )  # fmt: skip

    # ------------------------------------------------------------------ setup

    def after_fork(self) -> None:
        """A forked child (``algorithm.overlap``) needs its own thread pool; the inherited one is
        kept, never destroyed (it would wait for threads that stayed in the parent)."""
        self._forked_pools, self._pool = [self._pool], rollout.Rollout(nthread=self.num_threads)

    def _setup_physics(self, num_threads: int | None) -> None:
        """The rollout thread pool and its buffers, the reset / restore flags, the render caches."""
        m, n = self.model, self.num_envs
        self.substeps = self.task_spec.substeps
        # rollout input: ctrl held over the substeps
        self._control = np.zeros((n, self.substeps, m.nu))
        self._traj = np.zeros((n, self.substeps, self._nstate))  # rollout output
        self._sensordata = np.zeros((n, self.substeps, m.nsensordata))
        self.num_threads = default_num_threads(n) if num_threads is None else int(num_threads)
        self._pool = rollout.Rollout(nthread=self.num_threads)
        self._datas = [mujoco.MjData(m) for _ in range(max(1, self.num_threads))]
        self._models = [m] * n
        self._chunk = max(1, n // (max(1, self.num_threads) * 4))

        # reset inside _step, not yet handed out by _reset
        self._pending_reset = np.zeros(n, dtype=bool)
        # set by load_env_state: the next full reset hands back the restored state
        self._restored = False
        self.last_reset_was_restore = False
        self._render_data: mujoco.MjData | None = None
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}

    def _setup_terms(self, cfg: NativeTaskConfig) -> None:
        """The term tables (``rlexp.envs.native.terms``) and the action arrays."""
        n = self.num_envs
        self._action_terms, self.action_dim = build_action_terms(cfg.actions, self)
        self.action = np.zeros((n, self.action_dim))  # the current (clipped) action
        self.prev_action = np.zeros((n, self.action_dim))  # the previous step's action
        self._startup_events, self._reset_events, self._interval_events = build_event_terms(
            cfg.events, self
        )
        self._observation_terms = build_observation_terms(cfg.observations, self)
        self._reward_terms = build_reward_terms(cfg.rewards, self)
        self.reward_names = [k for k, *_ in self._reward_terms]

    def _make_specs(self) -> None:
        n, dev = self.num_envs, self.device
        vector = Unbounded((n, self.obs_dim), dtype=torch.float32, device=dev)
        if self._table.images:  # DESIGN47 §1: vector + uint8 [C, H, W] images
            entries = {
                k: Bounded(0, 255, (n, *chw), dtype=torch.uint8, device=dev)
                for _, k, chw in self._table.images
            }
            vector = Composite(
                entries, **({"vector": vector} if self.obs_dim else {}), shape=(n,), device=dev
            )
        self.observation_spec = Composite(
            observation=vector,
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

    # ------------------------------------------------------------------ the MDP

    def _fire(self, events: list, env_ids: np.ndarray) -> None:
        for key, func, params, _ in events:
            try:
                func(self, env_ids, **params)
            except TERM_ERRORS as exc:
                raise named_error(exc, f"events.{key}") from exc

    def _reset_envs(self, env_ids: np.ndarray) -> None:
        """Put envs ``env_ids`` back to their initial state and fire the reset events (batched)."""
        self._state[env_ids] = self._init_state
        self._ctrl[env_ids] = self._init_ctrl
        self.action[env_ids] = 0.0
        self.prev_action[env_ids] = 0.0
        self.episode_step[env_ids] = 0
        self._v.version += 1
        self._fire(self._reset_events, env_ids)

    def _observe(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Every env's observation now: the vector [N, dim] and the images (obs_table.py)."""
        obs, _ = observe(self, self._observation_terms)
        return self._table.flatten(obs, self.num_envs), self._table.pixels(obs)

    def _keep(self, fresh: tuple, keep: np.ndarray) -> None:
        """The envs of ``keep`` hold their current observation; the rest take ``fresh``'s."""
        vector, images = fresh
        vector[keep] = self._v.current_obs[keep]
        for key, img in images.items():
            img[keep] = self._v.current_images[key][keep]
        self._v.current_obs, self._v.current_images = vector, images

    def _current(self) -> Any:
        """The current observation as the env emits it (a copy: a Tensor, or vector + images)."""
        return self._table.output(self._v.current_obs.copy(), self._v.current_images, self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.step_action(tensordict.get("action"))

    def autoreset_observation(self, next_td: TensorDictBase) -> torch.Tensor:
        """The observation to act on after a ``step_action``: the step's own for running envs, the
        fresh reset one for envs that finished (reset inside the step); hands those resets out.
        What rlexp's collector uses instead of a masked ``reset()``."""
        self._pending_reset[:] = False
        return self._current()

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
                    except TERM_ERRORS as exc:
                        raise named_error(exc, f"events.{key}") from exc
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

        obs, images = self._observe()  # the true final observation of finished envs
        done = self.terminated | self.truncated
        self._v.current_obs, self._v.current_images = obs, images
        if done.any():
            ids = np.flatnonzero(done)
            self._reset_envs(ids)
            self._pending_reset[ids] = True
            self._keep(self._observe(), ~done)

        return self._tensordict(
            {
                "observation": self._table.output(obs, images, self.device),
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
            keep = np.ones(self.num_envs, dtype=bool)
            keep[ids] = False
            self._keep(self._observe(), keep)
        return self.current_tensordict()

    def current_tensordict(self) -> TensorDictBase:
        """The envs' current observation as a reset would return it (e.g. after ``load_state_dict``)."""
        n = self.num_envs
        zeros = torch.zeros((n, 1), dtype=torch.float32)
        false = torch.zeros((n, 1), dtype=torch.bool)
        return self._tensordict(
            {
                "observation": self._current(),
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
            **(
                {"current_images": {k: v.copy() for k, v in self._v.current_images.items()}}
                if self._table.images
                else {}
            ),
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
        saved = sd.get("current_images", {})
        self._v.current_images = {
            k: np.array(saved[k], dtype=np.uint8) for k in self._v.current_images
        }
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
        effects: bool = True,
        camera: str | None = None,
    ) -> np.ndarray:
        """An RGB frame (H, W, 3) uint8 of env ``env_id`` from a free camera at ``eye`` looking at
        ``target`` (or the model's camera named ``camera``).

        ``fovy`` (degrees) or pinhole ``intrinsics`` [fx, fy, cx, cy] (pixels) set the projection;
        neither: the model's default 45 degree field of view. ``effects=False``: no shadows,
        reflections or skybox (the camera observation term's frames).
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
            self.model,
            self._renderers,
            self.task_spec.asset,
            d,
            width,
            height,
            eye=eye if eye is not None else cam.get("eye", (2.0, -2.0, 2.0)),
            target=target if target is not None else cam.get("target", (0.0, 0.0, 0.0)),
            up=up,
            fovy=fovy,
            intrinsics=intrinsics,
            effects=effects,
            camera=camera,
        )

    def close(self, *args: Any, **kwargs: Any) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()
        super().close(*args, **kwargs)
