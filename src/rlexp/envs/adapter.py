"""What rlexp's Gymnasium-shaped backends share (``GymnasiumEnv``, ``AsyncGymnasiumEnv``,
``EnvPoolEnv``): TorchRL specs from an observation layout and action coding (``spaces.py``), Box
actions clipped to the box, the step output and the autoreset protocol of the lean collector, and
the resume bookkeeping (restored copies, restart seeds, the fallback when ``get_state`` fails).

A backend subclasses ``GymShapedEnv`` and provides ``step_tensors`` (one step of every copy; a
finished copy is reset inside it: its true final observation goes to ``"next"``, the reset one to
``_reset_obs`` with ``_pending_reset`` set), ``_full_reset``, ``_reset_copies``, and for resume
``_copy_states`` / ``_restore_copies`` (``state_kind``: ``mujoco`` | ``state`` | ``restart``).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import replace

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from rlexp.envs.env_state import RESTORED, restart_mode, restart_seed
from rlexp.envs.images import empty_obs, obs_from_state, obs_state
from rlexp.envs.spaces import ActionCoding, ObsLayout
from rlexp.envs.specs import obs_numpy, obs_tensor, set_specs

log = logging.getLogger(__name__)
#: Env ids whose action bounds were warned about in this process (``warn_action_bounds``).
_BOUNDS_WARNED: set[str] = set()


def _bounds(low: np.ndarray, high: np.ndarray) -> str:
    """Bounds for a message: ``[0, 5]`` when every dimension has the same, else per dimension."""
    if np.all(low == low[0]) and np.all(high == high[0]):
        return f"[{low[0]:g}, {high[0]:g}]"
    return f"low={[float(v) for v in low]} high={[float(v) for v in high]}"


class GymShapedEnv(EnvBase):
    """``num_envs`` copies of a Gymnasium-spaced task as one TorchRL env of rlexp's shape."""

    #: the ``env.backend`` this class implements
    backend = "gymnasium"
    #: how a checkpoint holds these envs mid-episode (``env_state``): mujoco | state | restart
    state_kind = "restart"
    #: why an env of this kind holds no state (the restart's ``resume_mode``)
    no_state_reason = "the env offers no get_state()/set_state()"

    def __init__(
        self,
        env_id: str,
        num_envs: int,
        layout: ObsLayout,
        coding: ActionCoding,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__(batch_size=torch.Size([num_envs]), device=device)
        self.env_id = env_id
        self.num_envs = n = num_envs
        #: how observations become the policy's flat vector, and actions the env's (spaces.py)
        self.obs_layout = layout
        self.action_coding = coding
        self.obs_dim = layout.dim
        self.act_dim = coding.dim
        set_specs(self, n, self.obs_dim, coding, layout)
        if coding.categorical:
            self._low = self._high = None
        else:
            self._low = np.asarray(coding.low, dtype=np.float64)
            self._high = np.asarray(coding.high, dtype=np.float64)
        self._state_warned = False
        #: env.rescale_actions: (low, (high - low) / 2) of the env's Box (None: act as given)
        self._rescale: tuple[np.ndarray, np.ndarray] | None = None
        self._seed: int | None = None  # seeds the next full reset (then None: streams continue)
        self._base_seed: int | None = (
            None  # the seed given to set_seed (restart seeds derive from it)
        )
        # Observations in numpy: float32 [n, obs_dim], or with images an ``ObsBatch`` (images.py)
        self._reset_obs = empty_obs(layout, n)
        # What changes every step lives in a plain object: EnvBase's __setattr__ costs ~3 us a call.
        self._live = _Live(empty_obs(layout, n))
        self._pending_reset = np.zeros(n, dtype=bool)
        self._restored = np.zeros(n, dtype=bool)  # copies whose state came from load_env_state
        self.last_reset_was_restore = False
        #: what the last load_env_state did (None before one): restored | restarted, and how
        self.resume_mode: str | None = None

    # -- what a backend provides -------------------------------------------------------------------
    def step_tensors(self, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """One step of every copy: ``observation``, ``reward``, ``done``, ``terminated``,
        ``truncated`` (``step_output``); finished copies reset inside it."""
        raise NotImplementedError

    def _full_reset(self) -> np.ndarray:
        """Every copy's observation after a full reset [n, obs_dim]: restored copies as restored,
        the others reset (seeded from ``_seed`` when set; it is cleared)."""
        raise NotImplementedError

    def _reset_copies(self, ids: np.ndarray) -> np.ndarray:
        """Reset copies ``ids`` now; their first observations [len(ids), obs_dim]."""
        raise NotImplementedError

    def _copy_states(self, kind: str) -> list[dict]:
        """Every copy's checkpoint entry (``env_state.copy_state``) for ``kind``."""
        return [{} for _ in range(self.num_envs)]

    def _restore_copies(self, kind: str, copies: list[dict]) -> np.ndarray:
        """Restore every copy from its entry; which copies were restored (bool [n])."""
        raise NotImplementedError

    # -- stepping ----------------------------------------------------------------------------------
    def _set_seed(self, seed: int | None) -> None:
        self._seed = self._base_seed = seed

    def clipped_actions(self, action: torch.Tensor) -> np.ndarray:
        """The policy's actions [n, A] as numpy: Box actions float64, clipped to the box;
        categorical ones the int64 indices."""
        return self.clip_array(action.detach().cpu().numpy())

    def clip_array(self, raw: np.ndarray) -> np.ndarray:
        """``clipped_actions`` of actions already in numpy (a new array: ``raw`` is left as it is);
        with ``rescale_actions`` clipped to [-1, 1], then mapped onto the env's bounds."""
        if self._low is None:
            return raw
        raw = raw.astype(np.float64)
        np.clip(raw, self._low, self._high, out=raw)
        if self._rescale is not None:
            low, half = self._rescale
            raw += 1.0
            raw *= half
            raw += low
        return raw

    def rescale_actions(self) -> None:
        """``env.rescale_actions=true``: the policy acts in [-1, 1] (its spec's bounds), each
        action ``a`` becomes ``low + (a + 1) * (high - low) / 2`` for the env; ``ValueError`` (one
        line) for categorical actions or a Box with an unbounded side."""
        coding = self.action_coding
        where = f"env.rescale_actions=true (env.name={self.env_id!r})"
        if coding.categorical:
            raise ValueError(
                f"{where}: the action space is {coding.kind}, not a Box; nothing to rescale: "
                "use env.rescale_actions=false"
            )
        low, high = np.asarray(coding.low), np.asarray(coding.high)
        if not (np.isfinite(low).all() and np.isfinite(high).all()):
            raise ValueError(
                f"{where}: the action bounds {_bounds(low, high)} have an unbounded side, which "
                "[-1, 1] cannot map onto: use env.rescale_actions=false"
            )
        unit = replace(coding, low=(-1.0,) * coding.dim, high=(1.0,) * coding.dim)
        set_specs(self, self.num_envs, self.obs_dim, unit, self.obs_layout)
        self._low, self._high = -np.ones(coding.dim), np.ones(coding.dim)
        self._rescale = (low, (high - low) / 2.0)

    def warn_action_bounds(self) -> None:
        """Once per env id and process: a finite Box whose bounds are not [-1, 1] (the Gaussian
        policy starts at mean 0 with std ~1, so early actions pile up at a bound or use a sliver
        of the range), as Stable-Baselines3 warns; ``env.rescale_actions=true`` is the fix."""
        coding = self.action_coding
        if coding.categorical or self._rescale is not None or self.env_id in _BOUNDS_WARNED:
            return
        low, high = np.asarray(coding.low), np.asarray(coding.high)
        if not (np.isfinite(low).all() and np.isfinite(high).all()):
            return
        if np.all(low == -1.0) and np.all(high == 1.0):
            return
        _BOUNDS_WARNED.add(self.env_id)
        kind = "not symmetric" if np.any(low != -high) else "not [-1, 1]"
        log.warning(
            "env.name=%r: the action bounds %s are %s; the Gaussian policy starts at mean 0 with "
            "std ~1, so early actions clip at a bound or use a sliver of the range: "
            "env.rescale_actions=true lets the policy act in [-1, 1] mapped onto the bounds",
            self.env_id,
            _bounds(low, high),
            kind,
        )

    def env_actions(self, action: torch.Tensor) -> np.ndarray:
        """The policy's actions as a vector env takes them, batched: Box actions clipped (and
        shaped as the space), categorical ones as the space's values (``decode_batch``)."""
        return self.action_coding.decode_batch(self.clipped_actions(action))

    def step_output(
        self, obs: np.ndarray, reward: np.ndarray, terminated: np.ndarray, truncated: np.ndarray
    ) -> dict[str, torch.Tensor]:
        """``step_tensors``' dict from the step's float32 observations [n, D], float32 rewards
        [n, 1] and bool flags [n, 1] (taken as they are: the tensors share their memory); counts
        the step. With images ``obs`` is an ``ObsBatch`` and the observation a TensorDict."""
        self.count_step(obs)
        return {
            "observation": obs_tensor(obs, self.num_envs),
            "reward": torch.from_numpy(reward),
            "done": torch.from_numpy(terminated | truncated),
            "terminated": torch.from_numpy(terminated),
            "truncated": torch.from_numpy(truncated),
        }

    def count_step(self, obs: np.ndarray) -> None:
        """Count a step whose observations are ``obs`` (float32 [n, D], not copied)."""
        self._live.steps += 1
        self._live.obs_now = obs

    def vector_output(
        self, obs: np.ndarray, reward: np.ndarray, terminated: np.ndarray, truncated: np.ndarray
    ) -> dict[str, torch.Tensor]:
        """``step_output`` from a vector env's batch: rewards and flags of shape [n], any dtype."""
        n = self.num_envs
        return self.step_output(
            obs,
            np.asarray(reward, dtype=np.float32).reshape(n, 1),
            np.asarray(terminated, dtype=bool).reshape(n, 1),
            np.asarray(truncated, dtype=bool).reshape(n, 1),
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.step_action(tensordict.get("action"))

    def step_action(self, action: torch.Tensor) -> TensorDictBase:
        """One step of every copy from an action tensor (the body of ``_step``)."""
        out = self.step_tensors(action)
        if self.device.type == "cpu":  # shapes and dtypes are ours: skip validation (~25 us)
            return TensorDict._new_unsafe(out, batch_size=self.batch_size, device=self.device)
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def autoreset_observation(
        self, next_td: TensorDictBase | Mapping[str, torch.Tensor]
    ) -> torch.Tensor:
        """The observation to act on after a ``step_action`` (or ``step_tensors``): the step's own
        for running copies, the fresh reset one for copies that finished (reset inside the step);
        hands those resets out. What rlexp's collector uses instead of a masked ``reset()``."""
        obs = next_td.get("observation")
        if self._pending_reset.any():
            obs = obs_tensor(self.autoreset_array(obs_numpy(obs)), self.num_envs)
        return obs

    def autoreset_array(self, obs: np.ndarray) -> np.ndarray:
        """``autoreset_observation`` of a step's observations in numpy (``step_arrays``'): a new
        array where copies finished, ``obs`` itself otherwise."""
        if self._pending_reset.any():
            obs = obs.copy()
            idx = np.flatnonzero(self._pending_reset)
            obs[idx] = self._reset_obs[idx]
            self._live.obs_now = obs
            self._pending_reset[:] = False
        return obs

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(-1).cpu().numpy().astype(bool)
        self.last_reset_was_restore = mask is None and bool(self._restored.all())
        if mask is None:
            obs = self._full_reset()
            self._restored[:] = False
        else:  # TorchRL's loop: copies reset inside _step hand out their cached observation
            obs = self._live.obs_now.copy()
            cached = mask & self._pending_reset
            obs[cached] = self._reset_obs[cached]
            fresh = np.flatnonzero(mask & ~self._pending_reset)
            if fresh.size:
                obs[fresh] = self._reset_copies(fresh)
        self._pending_reset[slice(None) if mask is None else mask] = False
        self._live.obs_now = obs
        return TensorDict(
            {"observation": obs_tensor(obs, self.num_envs)},
            batch_size=self.batch_size,
            device=self.device,
        )

    # -- resume ------------------------------------------------------------------------------------
    # A checkpoint holds the training envs mid-episode in one of three ways (``state_kind``,
    # docs/envs.md): ``mujoco`` (the integration state of a Gymnasium MuJoCo env: bit-exact),
    # ``state`` (the env's own ``get_state()`` / ``set_state(state)``), ``restart`` (nothing of
    # the env: on resume every copy starts a new episode, seeded from the checkpoint).
    def env_state(self, strict: bool = False) -> dict:
        """The state of every copy mid-episode, as plain data (``state_kind`` says what it holds).

        Saving never fails because of the env: a ``get_state()`` that raises or returns what a
        checkpoint cannot hold is logged once and this checkpoint holds the ``restart`` kind
        (``strict``: raise instead; the config check does, before the run starts)."""
        kind = self.state_kind
        try:
            copies = self._copy_states(kind)
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
            copies = self._copy_states(kind)
        return {
            "env_id": self.env_id,
            "kind": kind,
            "copies": copies,
            "obs": obs_state(self._live.obs_now),
            "reset_obs": obs_state(self._reset_obs),
            "pending_reset": self._pending_reset.copy(),
            "steps": self._live.steps,
            "seed": self._base_seed,
        }

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
        self._restored[:] = self._restore_copies(kind, list(sd["copies"]))
        if "obs" in sd:
            self._live.obs_now = obs_from_state(sd["obs"])
        self._reset_obs[:] = obs_from_state(sd["reset_obs"])
        self._pending_reset[:] = np.asarray(sd["pending_reset"])
        self._seed = None
        self.resume_mode = RESTORED[kind]

    def _restart_from(self, sd: dict, kind: str) -> None:
        """Every copy starts a new episode at the next full reset, seeded from the checkpoint's
        seed and step count (the same checkpoint always restarts the same way)."""
        self._seed = restart_seed(sd, self._base_seed, self._live.steps)
        self._restored[:] = False
        self._pending_reset[:] = False
        self.resume_mode = restart_mode(self._seed, kind, self.state_kind, self.no_state_reason)


class _Live:
    """Per-step state of an adapter: the steps taken (restart seeds derive from it) and what each
    copy shows now (replaced, never written in place: it may be a step's returned array)."""

    __slots__ = ("obs_now", "steps")

    def __init__(self, obs_now: np.ndarray) -> None:
        self.obs_now = obs_now
        self.steps = 0
