"""What the two batched torch contracts (``vecenv.py``, ``torchrl_env.py``) share: rlexp's env shape
on the env's own device, the autoreset bookkeeping, the first-step checks of what a user env
returns, and resume through the env's ``get_state()`` / ``set_state(state)`` (docs/batched_envs.md).

The rlexp shape: ``observation`` float32 [N, D], the action spec ``Bounded`` float32 [N, A] (its
bounds +-inf where the env states none) or ``MultiCategorical`` int64 [N, K], reward float32 [N, 1],
done / terminated / truncated bool [N, 1]. The env resets a finished copy inside its step: the step's
``"next"`` observation is the copy's true final one (or the documented stand-in, ``vecenv.py``), and
``autoreset_observation`` hands out the reset one, which the policy acts on next.

Nothing in the step path reads a value back to the host: tensors stay on the env's device, and what
a user env returns is checked once, at its first step (shapes, dtypes, devices), then trusted.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from rlexp.envs.env_state import plain_state
from rlexp.envs.spaces import ActionCoding, ObsLayout, ObsPart
from rlexp.envs.specs import set_specs
from rlexp.runtime.devices import same_device

log = logging.getLogger(__name__)

#: Floating dtypes an observation or reward may have (cast to float32; anything else is refused).
FLOATS = (torch.float16, torch.bfloat16, torch.float32, torch.float64)


def flat_layout(key: str, shape: tuple[int, ...], name: str = "Tensor") -> ObsLayout:
    """The layout of one observation tensor of per-env ``shape``, flattened (C order)."""
    size = 1
    for s in shape:
        size *= int(s)
    part = ObsPart(key, "box", tuple(int(s) for s in shape), 0, size)
    return ObsLayout(name, (part,), size, plain=len(shape) == 1)


def check_tensor(
    where: str,
    what: str,
    value: Any,
    shape: tuple[int, ...] | None,
    dtypes: tuple[torch.dtype, ...] | None,
    device: torch.device,
) -> torch.Tensor:
    """``value`` when it is a tensor of ``shape`` (None: any), a dtype of ``dtypes`` (None: any)
    on ``device``; a TypeError / ValueError of one line naming the env and the problem otherwise."""
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{where}: {what} is a {type(value).__name__}, not a torch.Tensor")
    if shape is not None and tuple(value.shape) != tuple(shape):
        raise ValueError(f"{where}: {what} has shape {list(value.shape)}, expected {list(shape)}")
    if dtypes is not None and value.dtype not in dtypes:
        names = ", ".join(str(d).replace("torch.", "") for d in dtypes)
        raise TypeError(f"{where}: {what} has dtype {value.dtype}, expected one of {names}")
    if not same_device(value.device, device):
        raise ValueError(
            f"{where}: {what} is on {value.device}, but the env says it lives on {device} "
            "(its device attribute): return every tensor on the env's device"
        )
    return value


class _Live:
    """Per-step state in a plain object (``EnvBase.__setattr__`` costs ~3 us a call): the
    observation the policy acts on next, the steps taken, whether the first step was checked."""

    __slots__ = ("checked", "obs_now", "steps")

    def __init__(self, obs_now: torch.Tensor) -> None:
        self.obs_now = obs_now
        self.steps = 0
        self.checked = False


class BatchedAdapter(EnvBase):
    """A batched torch env in rlexp's shape. Subclasses give ``_raw_reset`` (the flat observation
    after a full reset), ``_raw_step`` (one step of every copy), ``_raw_seed`` and the raw env's
    ``get_state`` / ``set_state`` (``self.raw``)."""

    #: what the env is called in messages (overridden by the contract)
    contract = "batched env"

    def __init__(
        self,
        raw: Any,
        name: str,
        num_envs: int,
        device: torch.device,
        obs_layout: ObsLayout,
        coding: ActionCoding,
    ) -> None:
        # not an nn.Module attribute: a TorchRL env would become a submodule of this one
        object.__setattr__(self, "raw", raw)
        self.env_id = name
        self.where = f"env.name={name!r}"
        self.num_envs = n = num_envs
        #: how the env's observation became the flat vector (checkpoints, export metadata)
        self.obs_layout = obs_layout
        #: the action the policy outputs and how it becomes the env's (spaces.ActionCoding)
        self.action_coding = coding
        super().__init__(batch_size=torch.Size([n]), device=device)
        self.obs_dim, self.act_dim = obs_layout.dim, coding.dim
        set_specs(self, n, self.obs_dim, coding, obs_layout)
        dev = self.device
        if coding.categorical:
            self._start = torch.tensor(coding.start, dtype=torch.int64, device=dev)
            self._low = self._high = None
        else:
            low = torch.tensor(coding.low, dtype=torch.float32, device=dev)
            high = torch.tensor(coding.high, dtype=torch.float32, device=dev)
            bounded = any(abs(v) != float("inf") for v in (*coding.low, *coding.high))
            self._low, self._high = (low, high) if bounded else (None, None)  # None: no clip
            self._start = None
        get, put = getattr(raw, "get_state", None), getattr(raw, "set_state", None)
        #: how a checkpoint holds the env mid-episode: state (its get_state) | restart
        self.state_kind = "state" if callable(get) and callable(put) else "restart"
        self._state_warned = False
        self._base_seed: int | None = None
        self._restored = False  # the next full reset hands back the restored observation
        #: what the last load_env_state did (None before one): restored | restarted, and how
        self.resume_mode: str | None = None
        obs_spec = self.observation_spec["observation"]  # a TensorDict of zeros with images
        self._live = _Live(
            obs_spec.zero() if obs_layout.structured else torch.zeros(n, self.obs_dim, device=dev)
        )

    # -- what a contract gives -----------------------------------------------------------------------
    def _raw_reset(self) -> torch.Tensor:
        raise NotImplementedError

    def _raw_step(
        self, action: Any, prev: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(obs after the autoreset, "next" obs, reward [N,1] f32, done [N,1], truncated [N,1])."""
        raise NotImplementedError

    def _raw_seed(self, seed: int) -> bool:
        """Seed the env's own RNG; False where it cannot be seeded."""
        raise NotImplementedError

    def _env_action(self, action: torch.Tensor) -> torch.Tensor:
        """The policy's action as the env takes it (a contract may reshape it further): Box
        actions clipped to the bounds the env states, categorical indices plus each ``start``."""
        if self._start is not None:
            return action + self._start
        if self._low is not None:
            return torch.clamp(action, self._low, self._high)
        return action

    # -- TorchRL API ---------------------------------------------------------------------------------
    def _set_seed(self, seed: int | None) -> None:
        self._base_seed = seed
        if seed is not None:
            self._raw_seed(int(seed))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        masked = tensordict is not None and "_reset" in tensordict.keys()
        if masked:  # TorchRL's loop after a step: those copies were reset inside the step
            obs = self._live.obs_now
        elif self._restored:  # resumed: the state the checkpoint holds, not a new episode
            self._restored = False
            obs = self._live.obs_now
        else:
            obs = self._live.obs_now = self._raw_reset()
        return TensorDict({"observation": obs}, batch_size=self.batch_size, device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.step_action(tensordict.get("action"))

    def step_action(self, action: torch.Tensor) -> TensorDictBase:
        """One step of every copy from an action tensor (the body of ``_step``)."""
        out = self.step_tensors(action)
        return TensorDict._new_unsafe(out, batch_size=self.batch_size, device=self.device)

    def step_tensors(self, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """``step_action``'s entries as a plain dict (what rlexp's collector stacks)."""
        live = self._live
        obs, nxt, reward, done, truncated = self._raw_step(self._env_action(action), live.obs_now)
        live.obs_now = obs
        live.steps += 1
        return {
            "observation": nxt,
            "reward": reward,
            "done": done,
            "terminated": done & ~truncated,
            "truncated": truncated,
        }

    def autoreset_observation(
        self, next_td: TensorDictBase | Mapping[str, torch.Tensor]
    ) -> torch.Tensor:
        """The observation to act on after a step: finished copies were reset inside it."""
        return self._live.obs_now

    def check_first_step(self) -> None:
        """The config check: a reset and one step of a zero action, so that what the env returns
        is checked (one line naming the problem) before the run starts."""
        self.reset()
        spec = self.action_spec
        self.step_action(torch.zeros(spec.shape, dtype=spec.dtype, device=self.device))

    # -- resume --------------------------------------------------------------------------------------
    def env_state(self, strict: bool = False) -> dict:
        """The env mid-episode as plain data: its ``get_state()`` (``state``) or nothing of it
        (``restart``); the observation to act on next, the steps taken, the seed. A ``get_state``
        that fails is logged once and the checkpoint holds ``restart`` (``strict``: raise)."""
        kind, state, on_device = self.state_kind, None, []
        if kind == "state":
            try:
                raw = self.raw.get_state()
                on_device = _tensor_paths(raw, self.device)
                state = plain_state(raw, self.env_id)
            except Exception as exc:
                if strict:
                    raise
                if not self._state_warned:
                    self._state_warned = True
                    log.warning(
                        "%s: get_state() failed (%s: %s); checkpoints hold no env state and a "
                        "resumed run starts new episodes", self.where, type(exc).__name__, exc,
                    )  # fmt: skip
                kind = "restart"
        return {
            "env_id": self.env_id,
            "kind": kind,
            "num_envs": self.num_envs,
            "state": state,
            "on_device": on_device,  # paths of the state's tensors that lived on the env's device
            "obs": _obs_state(self._live.obs_now),
            "steps": self._live.steps,
            "seed": self._base_seed,
            **(self._extra_state() if kind == "state" else {}),
        }

    def _extra_state(self) -> dict:
        """More of the adapter's own state a ``state`` checkpoint needs (plain data)."""
        return {}

    def _load_extra(self, sd: dict) -> None:
        """Put ``_extra_state()`` back."""

    def load_env_state(self, sd: dict) -> None:
        """Restore ``env_state()``: the next full ``reset()`` continues from it (``state``), or
        starts new episodes seeded from the checkpoint (``restart``); ``resume_mode`` says which."""
        if sd.get("env_id") != self.env_id or int(sd.get("num_envs", -1)) != self.num_envs:
            raise ValueError(
                f"env state is for {sd.get('env_id')} x{sd.get('num_envs')}; this env is "
                f"{self.env_id} x{self.num_envs}"
            )
        kind = sd.get("kind", "restart")
        self._live.steps = int(sd.get("steps", 0))
        if kind != self.state_kind or kind == "restart":
            self._restart_from(sd, kind)
            return
        self.raw.set_state(_to_device(sd["state"], set(sd.get("on_device", [])), self.device))
        obs = sd["obs"]
        if isinstance(obs, Mapping):  # with images: the TensorDict's entries (uint8 kept)
            self._live.obs_now = TensorDict(obs, batch_size=self.batch_size).to(self.device)
        else:
            self._live.obs_now = torch.as_tensor(obs).to(self.device, torch.float32)
        self._load_extra(sd)
        self._restored = True
        self.resume_mode = "restored (the env's get_state)"

    def _restart_from(self, sd: dict, kind: str) -> None:
        """New episodes at the next full reset, seeded from the checkpoint's seed and step count
        (the same checkpoint always restarts the same way, where the env can be seeded)."""
        base = sd.get("seed")
        base = self._base_seed if base is None else int(base)
        seed = ((0 if base is None else base) + 1_000_003 * self._live.steps) % 2**31
        self._restored = False
        if kind == self.state_kind:
            why = "the env offers no get_state()/set_state()"
        elif kind == "restart":
            why = "the checkpoint holds no env state (get_state() failed when it was saved)"
        else:
            why = f"the checkpoint holds a {kind!r} env state, this env's is {self.state_kind!r}"
        if self._raw_seed(seed):
            self.resume_mode = f"restarted (new episodes seeded {seed}: {why})"
        else:
            self.resume_mode = f"restarted (new episodes, unseeded: the env has no seed(); {why})"

    def close(self, *, raise_if_closed: bool = True) -> None:
        closer = getattr(self.raw, "close", None)
        if callable(closer):
            closer()
        super().close(raise_if_closed=raise_if_closed)


def _obs_state(obs: torch.Tensor | TensorDictBase) -> Any:
    """The observation to act on next as checkpoint data (with images: a dict of its entries)."""
    if isinstance(obs, TensorDictBase):
        return {k: v.detach().cpu().clone() for k, v in obs.items()}
    return obs.detach().cpu().clone()


def _tensor_paths(state: Any, device: torch.device, path: str = "") -> list[str]:
    """The paths (``a/0/b``) of the tensors in ``state`` that live on ``device`` (not the CPU:
    ``set_state`` gets them back there; an RNG's CPU state stays on the CPU)."""
    if isinstance(state, torch.Tensor):
        return [path] if state.device.type != "cpu" and same_device(state.device, device) else []
    if isinstance(state, Mapping):
        return [p for k, v in state.items() for p in _tensor_paths(v, device, f"{path}/{k}")]
    if isinstance(state, list | tuple):
        return [p for i, v in enumerate(state) for p in _tensor_paths(v, device, f"{path}/{i}")]
    return []


def _to_device(state: Any, paths: set[str], device: torch.device, path: str = "") -> Any:
    """``state`` with the tensors at ``paths`` moved back to ``device``."""
    if isinstance(state, torch.Tensor):
        return state.to(device) if path in paths else state
    if isinstance(state, dict):
        return {k: _to_device(v, paths, device, f"{path}/{k}") for k, v in state.items()}
    if isinstance(state, list | tuple):
        return type(state)(_to_device(v, paths, device, f"{path}/{i}") for i, v in enumerate(state))
    return state
