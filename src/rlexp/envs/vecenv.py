"""``env.backend=vecenv``: a batched torch env of rsl_rl's ``VecEnv`` contract as an rlexp env.

What rlexp reads of the env (docs/batched_envs.md): ``num_envs``, ``num_actions``, ``device``;
``get_observations()`` returning the policy's observation as a tensor [N, ...], as rsl_rl 2.x's
``(obs, extras)`` (more groups in ``extras["observations"]``, e.g. ``"critic"``), or as rsl_rl 3.x's
TensorDict / dict of observation groups (a ``"policy"`` group required). Every group is emitted: each
a part of the flat vector keyed and grouped by its name (a group that is a dict of terms: one part
per term, ``group/term``), the ``policy`` group first, the others by name (docs/envs.md); ``step(actions [N, A]) -> (obs, rewards [N], dones [N], extras)`` with the
time-outs in ``extras["time_outs"]``; optionally ``reset()``, ``seed(seed)``, ``get_state()`` /
``set_state(state)``, and a Gymnasium ``single_action_space`` / ``action_space`` (the action bounds,
or discrete actions; without one: unbounded float actions of ``num_actions``).

The env resets finished copies inside ``step``: ``terminated = dones & ~time_outs``, ``truncated =
dones & time_outs``. A truncated episode bootstraps from its true final observation when the env
hands it over as ``extras["final_observation"]`` (the observation's own form, every copy's
observation before its reset; only finished copies' rows are read). Without it rlexp does what
rsl_rl does: a time-out bootstraps from V of the observation the policy acted on (rsl_rl adds
``gamma * V(s_t)`` to a time-out's reward); here that observation stands in as the step's ``"next"``
one, so GAE computes the same ``r + gamma * V(s_t) - V(s_t)``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from rlexp.envs.batched_base import FLOATS, BatchedAdapter, check_tensor, flat_layout
from rlexp.envs.images import VECTOR_KEY
from rlexp.envs.masks import MASK_KEY, MaskSpec
from rlexp.envs.spaces import ActionCoding, ObsLayout, ObsPart, action_coding

log = logging.getLogger(__name__)

#: The extras key of the true final observations (before the autoreset).
FINAL_OBS_KEY = "final_observation"
#: The extras key of the time-outs (rsl_rl's).
TIME_OUTS_KEY = "time_outs"
#: Dtypes a done or time-out flag may have (non-zero: set).
FLAGS = (torch.bool, torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64, *FLOATS)
#: What the contract asks of the env (rsl_rl's VecEnv), for messages.
CONTRACT = "rsl_rl's VecEnv: num_envs, num_actions, device, get_observations(), step(actions)"


#: A part of the observation: (key, group, tensor [N, ...]).
Part = tuple[str, str, torch.Tensor]


def _group_parts(name: str, value: Any) -> list[Part]:
    """One group's parts: the group as one part keyed by its name, or (a group that is itself a
    dict / TensorDict of terms, Isaac Lab's ``concatenate_terms=False``) one part per term, keyed
    ``group/term``, depth-first with each level's names sorted."""
    if isinstance(value, Mapping | TensorDictBase):
        return [
            p for k in sorted(value.keys(), key=str) for p in _group_parts(f"{name}/{k}", value[k])
        ]
    return [(name, name.split("/", 1)[0], value)]


def observation_parts(out: Any, where: str, what: str, extras: Any = None) -> list[Part]:
    """Every observation group in what ``get_observations()`` / ``step()`` returned, as parts in the
    flat vector's order (the ``policy`` group first, then the others by name): a tensor (one part,
    key "", group ``policy``), rsl_rl 2.x's ``(obs, extras)`` with the other groups in
    ``extras["observations"]`` (``critic``: key and group ``critic``), or rsl_rl 3.x's TensorDict /
    dict of groups (each group a part keyed and grouped by its name)."""
    if isinstance(out, tuple | list) and out:
        return observation_parts(out[0], where, what, out[1] if len(out) > 1 else extras)
    if isinstance(out, Mapping | TensorDictBase):
        if "policy" not in out.keys():
            raise ValueError(
                f"{where}: {what} is a {type(out).__name__} without a 'policy' group (its keys: "
                f"{sorted(map(str, out.keys()))}); rsl_rl 3.x's observation groups name the "
                "policy's 'policy'"
            )
        groups = {str(k): out[k] for k in out.keys()}
    else:
        groups = {"": out}
    more = (
        extras.get("observations", None) if isinstance(extras, Mapping | TensorDictBase) else None
    )
    if isinstance(more, Mapping | TensorDictBase):  # rsl_rl 2.x: extras["observations"]["critic"]
        for k in more.keys():
            if str(k) not in groups and str(k) != "policy":
                groups[str(k)] = more[k]
    order = sorted(groups, key=lambda g: (g not in ("", "policy"), g))
    parts = [p for g in order for p in _group_parts(g, groups[g])]
    if "" in groups:  # a bare tensor: the policy's, at the root
        parts[0] = ("", "policy", groups[""])
    return parts


class VecEnvAdapter(BatchedAdapter):
    """An rsl_rl-style ``VecEnv`` (``raw``) as rlexp's batched env, on the env's own device."""

    contract = "vecenv"

    def __init__(
        self, raw: Any, name: str, action_mask: str = "auto", mask_key: str = MASK_KEY
    ) -> None:
        where = f"env.name={name!r}"
        for attr in ("num_envs", "num_actions", "device"):
            if not hasattr(raw, attr):
                raise TypeError(f"{where}: the env has no {attr!r} attribute ({CONTRACT})")
        for method in ("get_observations", "step"):
            if not callable(getattr(raw, method, None)):
                raise TypeError(f"{where}: the env has no {method}() method ({CONTRACT})")
        try:
            n, num_actions = int(raw.num_envs), int(raw.num_actions)
            device = torch.device(raw.device)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise TypeError(
                f"{where}: num_envs, num_actions or device is unusable ({exc}); {CONTRACT}"
            ) from None
        parts = observation_parts(raw.get_observations(), where, "get_observations()")
        for key, _, obs in parts:
            if isinstance(obs, torch.Tensor) and obs.dtype == torch.uint8 and obs.dim() >= 4:
                raise TypeError(
                    f"{where}: {_what('get_observations()', key)} is a uint8 image "
                    f"{list(obs.shape)}; env.backend='vecenv' reads float groups only (images come "
                    "through env.backend=torchrl, gymnasium, gymnasium_async, envpool or native)"
                )
            check_tensor(where, _what("get_observations()", key), obs, None, FLOATS, device)
            if obs.dim() < 2 or obs.shape[0] != n:
                raise ValueError(
                    f"{where}: {_what('get_observations()', key)} has shape {list(obs.shape)}, "
                    f"expected [num_envs={n}, ...]"
                )
        coding = _coding(raw, n, num_actions, where)
        first = raw.get_observations()
        mask = _extras_mask(first, coding, action_mask, mask_key, where)
        layout = _layout(parts)
        if mask is not None:  # the observation: a TensorDict of the vector and the mask
            layout = replace(layout, plain=False, mask=mask)
        super().__init__(raw, name, n, device, layout, coding)
        #: each part's key and shape [N, ...], in the flat vector's order
        self._shapes = {key: tuple(obs.shape) for key, _, obs in parts}
        self._has_reset = callable(getattr(raw, "reset", None))
        self._seedable = callable(getattr(raw, "seed", None))
        self._no_time_outs = torch.zeros(n, 1, dtype=torch.bool, device=self.device)
        self._live.obs_now = self._with_mask(self._flat(parts), first, "get_observations()")

    def _with_mask(self, vector: torch.Tensor, extras: Any, what: str) -> Any:
        """``vector`` as the observation: itself, or with a mask the TensorDict of it and
        ``extras[key]`` (``extras``: a step's extras, or what ``get_observations()`` returned)."""
        mask = self.obs_layout.mask
        if mask is None:
            return vector
        if isinstance(extras, tuple | list):
            extras = extras[1] if len(extras) > 1 else None
        value = extras.get(mask.key, None) if isinstance(extras, Mapping | TensorDictBase) else None
        n, width = self.num_envs, mask.width
        if not isinstance(value, torch.Tensor) or value.numel() != n * width:
            got = list(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise ValueError(
                f"{self.where}: {what}'s extras[{mask.key!r}] is {got}; the action mask is "
                f"[num_envs={n}, sum(nvec)={width}] (nvec={list(mask.nvec)}) at every reset and step"
            )
        value = value.reshape(n, width).to(device=self.device, dtype=torch.bool)
        if not self._live.checked:  # (every step would cost a device sync)
            blocks = value.split(list(mask.nvec), -1)
            if not all(bool(b.any(-1).all()) for b in blocks):
                raise ValueError(
                    f"{self.where}: {what}'s extras[{mask.key!r}] allows no action of a component "
                    f"(nvec={list(mask.nvec)}); every component needs one valid value"
                )
        return TensorDict._new_unsafe(
            {VECTOR_KEY: vector, MASK_KEY: value}, batch_size=torch.Size([n]), device=self.device
        )

    def _flat(self, parts: list[Part], fill: torch.Tensor | None = None) -> torch.Tensor:
        """The parts as the flat float32 vector [N, dim]; a part they lack is taken from ``fill``
        (a final observation without the other groups: the stand-in's columns) or refused."""
        n = self.num_envs
        if len(parts) == 1 and len(self._shapes) == 1:
            return parts[0][2].reshape(n, self.obs_dim).to(torch.float32)
        given = {key: obs for key, _, obs in parts}
        cols = []
        for part in self.obs_layout.parts:
            obs = given.get(part.key)
            if obs is None:
                if fill is None:
                    raise ValueError(
                        f"{self.where}: the observation has no group {part.key!r} (it had at the "
                        f"start; it has {sorted(given)})"
                    )
                cols.append(fill[:, part.offset : part.offset + part.size])
            else:
                cols.append(obs.reshape(n, part.size).to(torch.float32))
        return torch.cat(cols, -1)

    # -- the contract ------------------------------------------------------------------------------
    def _raw_seed(self, seed: int) -> bool:
        if self._seedable:
            self.raw.seed(seed)
        return self._seedable

    def _raw_reset(self) -> torch.Tensor:
        if self._has_reset:
            self.raw.reset()
        parts = observation_parts(self.raw.get_observations(), self.where, "get_observations()")
        what = "get_observations() after reset()"
        self._check_parts(parts, what)
        return self._with_mask(self._flat(parts), self.raw.get_observations(), what)

    def _check_parts(self, parts: list[Part], what: str, partial: bool = False) -> None:
        """Each part against the shape it had at the start (``partial``: parts may be missing)."""
        keys = [key for key, _, _ in parts]
        if not partial and sorted(keys) != sorted(self._shapes):
            raise ValueError(
                f"{self.where}: {what} gives the groups {keys}; at the start it gave "
                f"{list(self._shapes)}"
            )
        for key, _, obs in parts:
            shape = self._shapes.get(key)
            if shape is None:
                raise ValueError(
                    f"{self.where}: {_what(what, key)} is a group the env did not give at the "
                    f"start ({list(self._shapes)})"
                )
            check_tensor(self.where, _what(what, key), obs, shape, FLOATS, self.device)

    def _raw_step(
        self, action: torch.Tensor, prev: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        out = self.raw.step(action)
        if not self._live.checked:  # the first step: what the env returns, then trusted
            self._check_step(out)
        obs_raw, rewards, dones, extras = out
        obs = self._flat(observation_parts(obs_raw, self.where, "step()'s observation", extras))
        reward = rewards.reshape(self.num_envs, 1).to(torch.float32)
        done = dones.reshape(self.num_envs, 1)
        if done.dtype != torch.bool:
            done = done != 0
        time_outs = None if extras is None else extras.get(TIME_OUTS_KEY, None)
        if time_outs is None:
            truncated = self._no_time_outs
        else:
            time_outs = time_outs.reshape(self.num_envs, 1)
            truncated = done & (time_outs if time_outs.dtype == torch.bool else time_outs != 0)
        final = None if extras is None else extras.get(FINAL_OBS_KEY, None)
        masked = self.obs_layout.mask is not None
        if masked:  # the vectors; the mask is the step's (the next one's: only V reads "next")
            prev = prev.get(VECTOR_KEY)
        if final is None:  # rsl_rl's stand-in: V of the observation acted on (module docstring)
            nxt = torch.where(done, prev, obs)
        else:
            fin = observation_parts(final, self.where, f"extras[{FINAL_OBS_KEY!r}]")
            # a group the final observation lacks (2.x hands over the policy's): the stand-in's
            nxt = torch.where(done, self._flat(fin, fill=prev), obs)
        if masked:
            obs = self._with_mask(obs, extras, "step()")
            nxt = obs.copy().set(VECTOR_KEY, nxt)
        return obs, nxt, reward, done, truncated

    def _check_step(self, out: Any) -> None:
        """The first step's return, against the contract (one line naming the problem)."""
        w, n, dev = self.where, self.num_envs, self.device
        if not isinstance(out, tuple | list) or len(out) != 4:
            raise TypeError(
                f"{w}: step() returned a {type(out).__name__}"
                + (f" of {len(out)}" if isinstance(out, tuple | list) else "")
                + "; expected (obs, rewards, dones, extras)"
            )
        obs_raw, rewards, dones, extras = out
        self._check_parts(observation_parts(obs_raw, w, "step()", extras), "step()")
        rows = [(n,), (n, 1)]
        for what, value, dtypes in (("rewards", rewards, FLOATS), ("dones", dones, FLAGS)):
            check_tensor(w, f"step()'s {what}", value, None, dtypes, dev)
            if tuple(value.shape) not in rows:
                raise ValueError(
                    f"{w}: step()'s {what} has shape {list(value.shape)}, expected [{n}] or [{n}, 1]"
                )
        if extras is not None and not isinstance(extras, Mapping | TensorDictBase):
            raise TypeError(f"{w}: step()'s extras is a {type(extras).__name__}, not a dict")
        keys = set() if extras is None else set(extras.keys())
        if TIME_OUTS_KEY in keys:
            value = check_tensor(w, "extras['time_outs']", extras[TIME_OUTS_KEY], None, FLAGS, dev)
            if tuple(value.shape) not in rows:
                raise ValueError(
                    f"{w}: extras['time_outs'] has shape {list(value.shape)}, expected [{n}]"
                )
        else:
            log.warning(
                "%s: step() gives no extras['time_outs']: every done is a termination (no "
                "bootstrapping at time limits)", w,
            )  # fmt: skip
        if FINAL_OBS_KEY in keys:
            what = f"extras[{FINAL_OBS_KEY!r}]"
            self._check_parts(observation_parts(extras[FINAL_OBS_KEY], w, what), what, True)
        self._live.checked = True


def _what(where: str, key: str) -> str:
    """A part's name in messages: ``step()'s observation`` / ``step()'s 'critic' group``."""
    return f"{where}'s observation" if key in ("", "policy") else f"{where}'s {key!r} group"


def _layout(parts: list[Part]) -> ObsLayout:
    """The flat vector's layout: each part flattened (C order), in ``parts``' order."""
    if len(parts) == 1:
        key, _, obs = parts[0]
        return flat_layout(key, tuple(obs.shape[1:]))
    out, offset = [], 0
    for key, group, obs in parts:
        shape = tuple(int(s) for s in obs.shape[1:])
        size = math.prod(shape)
        out.append(ObsPart(key, "box", shape, offset, size, group=group))
        offset += size
    return ObsLayout("groups", tuple(out), offset)


def _coding(raw: Any, n: int, num_actions: int, where: str) -> ActionCoding:
    """The actions: from the env's Gymnasium action space where it has one (a batched ``Box``
    [N, A] gives row 0's bounds), else unbounded float actions of ``num_actions``."""
    import gymnasium as gym

    space = getattr(raw, "single_action_space", None)
    if space is None:
        space = getattr(getattr(raw, "unwrapped", None), "single_action_space", None)
    if space is None:
        space = getattr(raw, "action_space", None)
        if isinstance(space, gym.spaces.Box) and len(space.shape) == 2 and space.shape[0] == n:
            space = gym.spaces.Box(space.low[0], space.high[0], dtype=space.dtype)
    if not isinstance(space, gym.spaces.Space):
        inf = float("inf")
        return ActionCoding(
            "box", (num_actions,), num_actions, low=(-inf,) * num_actions, high=(inf,) * num_actions
        )
    coding = action_coding(space, where)
    if coding.dim != num_actions:
        raise ValueError(
            f"{where}: the action space {space} has {coding.dim} "
            f"{'components' if coding.categorical else 'dimensions'}, but num_actions={num_actions}"
        )
    return coding


def _extras_mask(
    first: Any, coding: ActionCoding, mode: str, key: str, where: str
) -> MaskSpec | None:
    """``env.action_mask`` of a VecEnv: ``extras[key]`` of ``get_observations()`` (rsl_rl 2.x's
    ``(obs, extras)``) and of every ``step()`` (``auto``: when the first extras have it; ``info``:
    required); ``observation`` and a Box action space are refused in one line."""
    if mode == "off":
        return None
    extras = first[1] if isinstance(first, tuple | list) and len(first) > 1 else None
    has = isinstance(extras, Mapping | TensorDictBase) and key in extras.keys()
    if mode == "observation":
        raise ValueError(
            f"{where}: env.action_mask=observation reads a Dict observation key; a vecenv gives "
            f"its mask in extras[{key!r}]: use env.action_mask=info (or auto)"
        )
    if not coding.categorical:
        if mode == "auto":
            return None
        raise ValueError(
            f"{where}: env.action_mask={mode} masks categorical actions; the action space is a "
            "Box (continuous): use env.action_mask=off"
        )
    if not has:
        if mode == "auto":
            return None
        raise ValueError(
            f"{where}: env.action_mask=info reads extras[{key!r}] of get_observations() (rsl_rl "
            "2.x's (obs, extras)) and of every step(); get_observations() gives none: return "
            "(obs, extras) with the mask, or use env.action_mask=off"
        )
    return MaskSpec("info", key, tuple(coding.nvec))
