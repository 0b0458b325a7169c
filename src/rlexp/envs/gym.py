"""Gymnasium environments (the MuJoCo suite, classic control, the user's own) as batched TorchRL
environments.

``GymnasiumEnv`` is a lean ``EnvBase`` over ``num_envs`` Gymnasium copies: the spaces become
TorchRL specs (``spaces.py``: observations flattened to one float32 vector, Box actions clipped to
the box, categorical actions decoded to the env's space), and a finished copy is reset inside
``_step`` (its true final observation goes to ``"next"`` so truncated episodes bootstrap
correctly; the following masked ``_reset`` hands back the cached reset observation). It exists because TorchRL's ``GymEnv`` + ``DoubleToFloat`` costs ~0.4 ms of Python per
step here (measured: 1,065 steps/s for collection alone on HalfCheetah-v5 against 15,000 for raw
Gymnasium); ``env.backend=torchrl_gym`` still builds that reference path.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator, Mapping

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, MultiCategorical, Unbounded
from torchrl.envs import EnvBase

from rlexp.envs.env_state import (
    env_state_kind,
    has_reset,
    mujoco_state,
    plain_state,
    rng_state,
    set_mujoco_state,
    time_limit,
)
from rlexp.envs.spaces import action_coding, obs_layout

log = logging.getLogger(__name__)

#: The Gymnasium MuJoCo suite (any other registered id works too; these are the tested ones).
GYM_MUJOCO_TASKS = (
    "HalfCheetah-v5",
    "Hopper-v5",
    "Walker2d-v5",
    "Ant-v5",
    "InvertedPendulum-v5",
    "InvertedDoublePendulum-v5",
    "Humanoid-v5",
    "Swimmer-v5",
    "Reacher-v5",
)


def check_gym_id(env_id: str) -> None:
    """Raise a KeyError naming close matches when ``env_id`` is not a registered Gymnasium id.

    ``module:EnvId`` (Gymnasium's own syntax) imports ``module`` first, so that the package that
    registers ``EnvId`` does so; ids registered by an ``rlexp.plugins`` entry point are in the
    registry once the plugins are loaded (``rlexp train`` loads them at start-up)."""
    module, name = "", env_id
    if ":" in env_id:
        module, name = env_id.split(":", 1)
        import importlib

        try:
            importlib.import_module(module)
        except Exception as exc:  # ModuleNotFoundError, or the module's own failure
            from rlexp.config.rules import first_line

            raise KeyError(
                f"env.name={env_id!r}: module {module!r} could not be imported "
                f"({type(exc).__name__}: {first_line(exc)}); "
                "install the package that registers the env (pip install -e PATH)"
            ) from None
    if name in gym.registry:
        return
    import difflib

    close = difflib.get_close_matches(name, list(gym.registry), n=3)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    where = f" (module {module!r} was imported but did not register it)" if name != env_id else ""
    raise KeyError(
        f"env.name={env_id!r} is not a registered Gymnasium environment{where}; "
        f"MuJoCo tasks: {list(GYM_MUJOCO_TASKS)}{hint}; your own env: docs/envs.md"
    )


#: MuJoCo warnings about Gymnasium's own model files, not the user's: MuJoCo 4.0 deprecates the
#: ``settotalmass`` compiler attribute that gymnasium's HalfCheetah, Hopper, Walker2d... XML use.
IGNORED_MUJOCO_WARNINGS = ("compiler attribute 'settotalmass' is deprecated",)


@contextlib.contextmanager
def mujoco_build_warnings(env_id: str) -> Iterator[None]:
    """While Gymnasium compiles ``env_id``'s MuJoCo models: MuJoCo's warnings go to this module's
    logger instead of stdout and a ``MUJOCO_LOG.TXT`` in the working directory, and the deprecation
    of Gymnasium's own XML (twice per env copy, 22 lines per HalfCheetah run) is dropped. A handler
    someone else installed is left alone; stepping keeps MuJoCo's own handler."""
    try:
        entry = str(getattr(gym.spec(env_id), "entry_point", ""))
    except Exception:  # checked (and reported) by check_gym_id
        entry = ""
    if "mujoco" not in entry:  # a Gymnasium task that is not MuJoCo's: MuJoCo is not imported
        yield
        return
    import mujoco

    if mujoco.get_mju_user_warning() is not None:
        yield
        return

    def forward(message: str) -> None:
        if not message.startswith(IGNORED_MUJOCO_WARNINGS):
            log.warning("[mujoco] %s", message)

    mujoco.set_mju_user_warning(forward)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(None)


class GymnasiumEnv(EnvBase):
    """``num_envs`` copies of a Gymnasium env stepped in one process, as one TorchRL env."""

    def __init__(
        self,
        env_id: str,
        num_envs: int = 1,
        max_episode_steps: int | None = None,
        make_kwargs: dict | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        check_gym_id(env_id)
        os.environ.setdefault("MUJOCO_GL", "egl")
        kwargs = dict(make_kwargs or {})
        if max_episode_steps is not None:
            kwargs["max_episode_steps"] = max_episode_steps
        self.env_id = env_id
        self.num_envs = num_envs
        with mujoco_build_warnings(env_id):
            self._envs = [gym.make(env_id, **kwargs) for _ in range(num_envs)]
        obs_space = self._envs[0].observation_space
        act_space = self._envs[0].action_space
        where = f"env.name={env_id!r}"
        #: how observations become the policy's flat vector, and actions the env's (spaces.py)
        self.obs_layout = obs_layout(obs_space, where)
        self.action_coding = action_coding(act_space, where)
        super().__init__(batch_size=torch.Size([num_envs]), device=device)
        self.obs_dim = self.obs_layout.dim
        self.act_dim = self.action_coding.dim
        self._plain_obs = self.obs_layout.plain
        self._reshape_actions = len(self.action_coding.shape) != 1
        n = num_envs
        self.observation_spec = Composite(
            observation=Unbounded(shape=(n, self.obs_dim), dtype=torch.float32, device=self.device),
            shape=(n,),
            device=self.device,
        )
        if self.action_coding.categorical:
            self._low = self._high = None
            self.action_spec = MultiCategorical(
                nvec=list(self.action_coding.nvec),
                shape=(n, self.act_dim),
                dtype=torch.int64,
                device=self.device,
            )
        else:
            self._low = np.asarray(self.action_coding.low, dtype=np.float64)
            self._high = np.asarray(self.action_coding.high, dtype=np.float64)
            self.action_spec = Bounded(
                low=torch.as_tensor(self._low, dtype=torch.float32).expand(n, self.act_dim).clone(),
                high=torch.as_tensor(self._high, dtype=torch.float32)
                .expand(n, self.act_dim)
                .clone(),
                shape=(n, self.act_dim),
                dtype=torch.float32,
                device=self.device,
            )
        self.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            done=Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device),
            terminated=Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device),
            truncated=Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device),
            shape=(n,),
            device=self.device,
        )
        #: how a checkpoint holds these envs mid-episode (``env_state``): mujoco | state | restart
        self.state_kind = env_state_kind(self._envs[0])
        self._state_warned = False
        self._seed: int | None = None
        # the seed given to set_seed (restart seeds derive from it)
        self._base_seed: int | None = None
        self._reset_obs = np.zeros((n, self.obs_dim), dtype=np.float32)
        # What changes every step lives in a plain object: EnvBase's __setattr__ costs ~3 us a call.
        self._live = _Live(np.zeros((n, self.obs_dim), dtype=np.float32))
        self._pending_reset = np.zeros(n, dtype=bool)
        self._restored = np.zeros(n, dtype=bool)  # copies whose state came from load_env_state
        self.last_reset_was_restore = False
        #: what the last load_env_state did (None before one): restored | restarted, and how
        self.resume_mode: str | None = None

    # -- TorchRL API -------------------------------------------------------------------------------
    def _set_seed(self, seed: int | None) -> None:
        self._seed = self._base_seed = seed
        for i, env in enumerate(self._envs):
            env.action_space.seed(None if seed is None else seed + i)

    def _reset_one(self, i: int) -> np.ndarray:
        """Reset copy ``i``; its first observation, flattened."""
        if self._seed is not None:
            # Seed each copy once; later resets continue its own RNG stream.
            obs, _ = self._envs[i].reset(seed=self._seed + i)
        else:
            obs, _ = self._envs[i].reset()
        return self.obs_layout.flatten(obs)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(-1).cpu().numpy()
        self.last_reset_was_restore = mask is None and bool(self._restored.all())
        if mask is None and self._restored.any():
            # Restored from a checkpoint: the first full reset hands back the restored state
            # (copies that had never been reset are reset as usual).
            restored, self._restored = self._restored, np.zeros(self.num_envs, dtype=bool)
            obs = np.stack(
                [
                    self._current_obs(i) if restored[i] else self._reset_one(i)
                    for i in range(self.num_envs)
                ]
            ).astype(np.float32)
            self._live.obs_now = obs
            return TensorDict(
                {"observation": torch.from_numpy(obs)},
                batch_size=self.batch_size,
                device=self.device,
            )
        obs = np.empty((self.num_envs, self.obs_dim), dtype=np.float32)
        for i in range(self.num_envs):
            if mask is not None and not mask[i]:
                continue
            if mask is not None and self._pending_reset[i]:
                obs[i] = self._reset_obs[i]  # already reset inside _step
            else:
                obs[i] = self._reset_one(i)
            self._pending_reset[i] = False
        if mask is None:
            self._live.obs_now = obs
        else:
            now = self._live.obs_now.copy()
            now[mask] = obs[mask]
            self._live.obs_now = now
        if self._seed is not None and mask is None:
            self._seed = None  # seeded once: further resets draw from each env's own stream
        return TensorDict(
            {"observation": torch.from_numpy(obs)}, batch_size=self.batch_size, device=self.device
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.step_action(tensordict.get("action"))

    def autoreset_observation(
        self, next_td: TensorDictBase | Mapping[str, torch.Tensor]
    ) -> torch.Tensor:
        """The observation to act on after a ``step_action`` (or ``step_tensors``): the step's own
        for running copies, the fresh reset one for copies that finished (reset inside the step);
        hands those resets out. What rlexp's collector uses instead of a masked ``reset()``."""
        obs = next_td.get("observation")
        if self._pending_reset.any():
            obs = obs.clone()
            idx = np.flatnonzero(self._pending_reset)
            obs[idx] = torch.from_numpy(self._reset_obs[idx])
            self._live.obs_now = obs.numpy()
            self._pending_reset[:] = False
        return obs

    def step_action(self, action: torch.Tensor) -> TensorDictBase:
        """One step of every copy from an action tensor (the body of ``_step``)."""
        out = self.step_tensors(action)
        if (
            self.device.type == "cpu"
        ):  # shapes and dtypes are ours: skip per-entry validation (~25 us)
            return TensorDict._new_unsafe(out, batch_size=self.batch_size, device=self.device)
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def step_tensors(self, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """``step_action``'s entries as a plain dict (the collector stacks a rollout's per key:
        ~15 ms less per 2048 steps than building and stacking a TensorDict per step)."""
        n = self.num_envs
        if self._low is None:  # categorical: int indices [n, K] -> the env's values
            raw = action.detach().cpu().numpy()
            actions = [self.action_coding.decode(raw[i]) for i in range(n)]
        else:
            actions = action.detach().cpu().numpy().astype(np.float64)
            np.clip(actions, self._low, self._high, out=actions)
            if self._reshape_actions:  # a Box of another shape than [act_dim]
                actions = [self.action_coding.decode(actions[i]) for i in range(n)]
        obs = np.empty((n, self.obs_dim), dtype=np.float32)
        reward = np.empty((n, 1), dtype=np.float32)
        terminated = np.zeros((n, 1), dtype=bool)
        truncated = np.zeros((n, 1), dtype=bool)
        flatten = None if self._plain_obs else self.obs_layout.flatten_into
        for i, env in enumerate(self._envs):
            o, r, term, trunc, _ = env.step(actions[i])
            if flatten is None:
                obs[i] = o
            else:
                flatten(obs[i], o)
            reward[i, 0] = r
            terminated[i, 0] = term
            truncated[i, 0] = trunc
            if term or trunc:
                self._reset_obs[i] = self._reset_one(i)
                self._pending_reset[i] = True
        self._live.steps += 1
        self._live.obs_now = obs
        return {
            "observation": torch.from_numpy(obs),
            "reward": torch.from_numpy(reward),
            "done": torch.from_numpy(terminated | truncated),
            "terminated": torch.from_numpy(terminated),
            "truncated": torch.from_numpy(truncated),
        }

    # -- resume ------------------------------------------------------------------------------------
    # A checkpoint holds the training envs mid-episode in one of three ways (``state_kind``,
    # docs/envs.md): ``mujoco`` (the integration state of a Gymnasium MuJoCo env: bit-exact),
    # ``state`` (the env's own ``get_state()`` / ``set_state(state)``: plain arrays, exact as far as
    # the env's state is complete), ``restart`` (nothing of the env: on resume every copy starts a
    # new episode, seeded from the checkpoint). Env objects are never pickled.
    def _current_obs(self, i: int) -> np.ndarray:
        if self._pending_reset[i]:
            return self._reset_obs[i]
        if self.state_kind == "mujoco":
            return self.obs_layout.flatten(self._envs[i].unwrapped._get_obs())
        return self._live.obs_now[i]

    def env_state(self, strict: bool = False) -> dict:
        """The state of every copy mid-episode, as plain data (``state_kind`` says what it holds).

        Saving never fails because of the env: a ``get_state()`` that raises or returns what a
        checkpoint cannot hold is logged once and this checkpoint holds the ``restart`` kind
        (``strict``: raise instead; the config check does, before the run starts)."""
        kind = self.state_kind
        try:
            copies = [self._copy_state(env, kind) for env in self._envs]
        except Exception as exc:
            if strict or kind != "state":
                raise
            if not self._state_warned:
                self._state_warned = True
                log.warning(
                    "env.name=%r: get_state() failed (%s: %s); checkpoints hold no env state and "
                    "a resumed run starts new episodes",
                    self.env_id,
                    type(exc).__name__,
                    exc,
                )
            kind = "restart"
            copies = [self._copy_state(env, kind) for env in self._envs]
        return {
            "env_id": self.env_id,
            "kind": kind,
            "copies": copies,
            "obs": self._live.obs_now.copy(),
            "reset_obs": self._reset_obs.copy(),
            "pending_reset": self._pending_reset.copy(),
            "steps": self._live.steps,
            "seed": self._base_seed,
        }

    def _copy_state(self, env: gym.Env, kind: str) -> dict:
        limit = time_limit(env)
        copy = {
            "rng": rng_state(env.unwrapped),
            "has_reset": has_reset(env),
            "elapsed_steps": -1  # no time limit, or not started
            if limit is None or limit._elapsed_steps is None
            else limit._elapsed_steps,
        }
        if kind == "mujoco":
            copy["physics"] = mujoco_state(env.unwrapped)
        elif kind == "state":
            copy["state"] = plain_state(env.unwrapped.get_state(), self.env_id)
        return copy

    def load_env_state(self, sd: dict) -> None:
        """Restore ``env_state()``: the next full ``reset()`` continues from it instead of resetting
        (``mujoco``, ``state``), or starts new episodes seeded from the checkpoint (``restart``);
        ``resume_mode`` says which happened."""
        if sd["env_id"] != self.env_id or len(sd["copies"]) != self.num_envs:
            raise ValueError(
                f"env state is for {sd['env_id']} x{len(sd['copies'])}; this env is "
                f"{self.env_id} x{self.num_envs}"
            )
        kind = sd.get("kind", "mujoco")  # checkpoints before #28 held MuJoCo envs only
        self._live.steps = int(sd.get("steps", 0))
        if kind != self.state_kind or kind == "restart":
            self._restart_from(sd, kind)
            return
        for i, (env, c) in enumerate(zip(self._envs, sd["copies"], strict=True)):
            if not c.get("has_reset", int(c["elapsed_steps"]) >= 0):
                continue  # never reset when saved: it will be reset as usual
            u = env.unwrapped
            if not has_reset(env):
                env.reset()  # gymnasium's OrderEnforcing wants a reset before step
            if kind == "mujoco":
                set_mujoco_state(u, c["physics"])
            else:
                u.set_state(c["state"])
            if c.get("rng") is not None:
                u.np_random.bit_generator.state = c["rng"]
            if time_limit(env) is not None and int(c["elapsed_steps"]) >= 0:
                time_limit(env)._elapsed_steps = int(c["elapsed_steps"])
            self._restored[i] = True
        if "obs" in sd:
            self._live.obs_now = np.array(sd["obs"], dtype=np.float32)
        self._reset_obs[:] = np.asarray(sd["reset_obs"])
        self._pending_reset[:] = np.asarray(sd["pending_reset"])
        self._seed = None
        self.resume_mode = (
            "restored (MuJoCo state)" if kind == "mujoco" else "restored (the env's get_state)"
        )

    def _restart_from(self, sd: dict, kind: str) -> None:
        """Every copy starts a new episode at the next full reset, seeded from the checkpoint's
        seed and step count (the same checkpoint always restarts the same way)."""
        base = sd.get("seed")
        base = self._base_seed if base is None else int(base)
        seed = ((0 if base is None else base) + 1_000_003 * self._live.steps) % 2**31
        self._seed = seed
        self._restored[:] = False
        self._pending_reset[:] = False
        if kind == self.state_kind:
            why = "the env offers no get_state()/set_state()"
        elif kind == "restart":
            why = "the checkpoint holds no env state (get_state() failed when it was saved)"
        else:
            why = f"the checkpoint holds a {kind!r} env state, this env's is {self.state_kind!r}"
        self.resume_mode = f"restarted (new episodes seeded {seed}: {why})"

    # -- extras ------------------------------------------------------------------------------------
    def render(self, env_id: int = 0, **camera) -> np.ndarray:
        """An RGB frame of copy ``env_id`` from Gymnasium's own camera (needs
        ``env.kwargs.render_mode=rgb_array``; size from ``env.kwargs.width/height``). Camera placement
        arguments (eye, target, intrinsics) apply to the native tasks only and are ignored here."""
        if self._envs[env_id].render_mode != "rgb_array":
            raise ValueError(
                f"env.name={self.env_id!r}: rendering needs env.kwargs.render_mode=rgb_array "
                "(e.g. +env.kwargs.render_mode=rgb_array on the command line)"
            )
        return self._envs[env_id].render()

    def close(self, *, raise_if_closed: bool = True) -> None:
        for env in self._envs:
            env.close()
        super().close(raise_if_closed=raise_if_closed)


class _Live:
    """Per-step state of ``GymnasiumEnv``: the steps taken (restart seeds derive from it) and what
    each copy shows now (replaced, never written in place: it may be a step's returned array)."""

    __slots__ = ("obs_now", "steps")

    def __init__(self, obs_now: np.ndarray) -> None:
        self.obs_now = obs_now
        self.steps = 0


def make_torchrl_gym_env(
    env_id: str, num_envs: int, max_episode_steps: int | None, make_kwargs: dict
):
    """The reference path: TorchRL's own ``GymEnv`` with a float32 cast (slower per step)."""
    from torchrl.envs import DoubleToFloat, GymEnv, TransformedEnv

    check_gym_id(env_id)
    space = gym.make(env_id, **dict(make_kwargs)).action_space
    if not isinstance(space, gym.spaces.Box):
        raise TypeError(
            f"env.name={env_id!r}: env.backend=torchrl_gym takes Box actions only (got "
            f"{type(space).__name__}); use env.backend=gymnasium"
        )
    kwargs = dict(make_kwargs)
    if max_episode_steps is not None:
        kwargs["max_episode_steps"] = max_episode_steps
    if num_envs > 1:
        from torchrl.envs import SerialEnv

        base = SerialEnv(num_envs, lambda: GymEnv(env_id, **kwargs))
    else:
        base = GymEnv(env_id, **kwargs)
    return TransformedEnv(base, DoubleToFloat())
