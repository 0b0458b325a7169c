"""Action masks (issue #48): which actions of a categorical action space are valid at a step.

Where a mask comes from (``env.action_mask``, docs/envs.md "Action masks"):

- ``observation``: a key of a ``Dict`` observation (``env.action_mask_key``, default
  ``action_mask``); that key is then not part of the policy's observation vector;
- ``info``: ``info[env.action_mask_key]`` of every ``reset`` and ``step`` (Gymnasium's convention,
  e.g. Taxi-v3 and the other toy-text envs);
- ``auto`` (the default): ``observation`` when the Dict observation has the key, else ``info`` when
  a probe reset's info has it, else no mask; ``off``: no mask (the key, if in the observation, is
  an ordinary part of it).

The mask is bool ``[sum(nvec)]`` per copy: per action component its ``nvec[k]`` entries,
concatenated (``MultiBinary(n)``: ``n`` pairs, entry 0 the value 0); a ``Discrete`` action's mask
may also come as its ``n`` entries of 0/1 ints (Taxi-v3's int8). It is the ``action_mask`` entry
(``MASK_KEY``) of the observation TensorDict the env emits, next to ``vector`` and any images, so
it travels with the observation through collection, the rollout, evaluation and checkpoints.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces

#: The observation TensorDict's entry (and the exported file's input) that holds the mask.
MASK_KEY = "action_mask"
#: ``env.action_mask``'s values.
MASK_MODES = ("auto", "info", "observation", "off")


@dataclass(frozen=True)
class MaskSpec:
    """Where a mask comes from and how wide it is."""

    source: str  # info | observation
    key: str  # the info key, or the observation's Dict key path
    nvec: tuple[int, ...]  # the action space's values per component

    @property
    def width(self) -> int:
        return int(sum(self.nvec))

    def record(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "key": self.key,
            "width": self.width,
            "nvec": list(self.nvec),
        }


def resolve_mask(
    mode: str,
    key: str,
    obs_space: spaces.Space,
    nvec: tuple[int, ...] | None,
    probe_info: Callable[[], dict] | None,
    where: str,
) -> MaskSpec | None:
    """``env.action_mask`` for an env of these spaces (``nvec``: None for a Box action space);
    ``probe_info``: a reset's info (only called for ``auto`` when the observation has no key).
    A mode that cannot apply is a one-line ``ValueError``."""
    if mode not in MASK_MODES:
        raise ValueError(f"env.action_mask={mode!r}; choose from {list(MASK_MODES)}")
    if mode == "off":
        return None
    in_obs = isinstance(obs_space, spaces.Dict) and key in {str(k) for k in obs_space.spaces}
    if nvec is None:
        if mode == "auto":
            return None
        raise ValueError(
            f"{where}: env.action_mask={mode} masks categorical actions; the action space is a "
            "Box (continuous): use env.action_mask=off"
        )
    if mode == "observation" or (mode == "auto" and in_obs):
        if not in_obs:
            have = sorted(map(str, obs_space.spaces)) if isinstance(obs_space, spaces.Dict) else []
            raise ValueError(
                f"{where}: env.action_mask=observation reads the Dict observation key "
                f"env.action_mask_key={key!r}; the observation space has keys {have}: set "
                "env.action_mask_key to the mask's key, or env.action_mask=info|off"
            )
        sub = obs_space.spaces[_dict_key(obs_space, key)]
        size = int(np.prod(sub.shape)) if sub.shape is not None else -1
        if size != sum(nvec):
            raise ValueError(_width_message(where, f"observation key {key!r}", size, nvec))
        return MaskSpec("observation", key, tuple(nvec))
    info = probe_info() if probe_info is not None else None
    if info is not None and key not in info:
        if mode == "auto":
            return None
        raise ValueError(
            f"{where}: env.action_mask=info reads info[{key!r}]; the env's reset gives info keys "
            f"{sorted(map(str, info))}: set env.action_mask_key to the mask's key, or "
            "env.action_mask=observation|off"
        )
    if info is None and mode == "auto":
        return None
    spec = MaskSpec("info", key, tuple(nvec))
    if info is not None:
        mask_encoder(spec, where)(info[key])  # the width and validity, now (one line if wrong)
    return spec


def _dict_key(space: spaces.Dict, key: str) -> Any:
    return next(k for k in space.spaces if str(k) == key)


def _width_message(where: str, what: str, got: int, nvec: tuple[int, ...]) -> str:
    return (
        f"{where}: the action mask ({what}) has {got} entries; expected sum(nvec)={sum(nvec)} "
        f"(nvec={list(nvec)}: one entry per value of each action component, concatenated)"
    )


def mask_encoder(spec: MaskSpec, where: str) -> Callable[[Any], np.ndarray]:
    """``raw mask -> bool [width]``; a mask of another width, or a component with no valid
    action, is a one-line ``ValueError`` (the policy could only act invalidly)."""
    width, nvec = spec.width, spec.nvec
    what = f"info[{spec.key!r}]" if spec.source == "info" else f"observation key {spec.key!r}"
    bounds = np.cumsum((0, *nvec))

    def encode(raw: Any) -> np.ndarray:
        if raw is None:
            raise ValueError(
                f"{where}: env.action_mask={spec.source} reads {what}, which this step does not "
                "give; give it at every reset and step, or use env.action_mask=off"
            )
        mask = np.asarray(raw).reshape(-1).astype(bool)
        if mask.size != width:
            raise ValueError(_width_message(where, what, mask.size, nvec))
        if not np.logical_or.reduceat(mask, bounds[:-1]).all():
            raise ValueError(
                f"{where}: the action mask ({what}) allows no action of a component "
                f"(nvec={list(nvec)}, mask={mask.astype(int).tolist()}); every component needs "
                "one valid value"
            )
        return mask

    return encode


def env_mask(env: Any, make: Callable[[], Any], coding: Any, mode: str, key: str, where: str):
    """``resolve_mask`` for a built Gymnasium env (``coding``: its ``spaces.ActionCoding``);
    ``auto`` probes a throwaway copy from ``make`` (its first reset's info) only where the
    actions are categorical and the observation has no mask key."""

    def probe() -> dict:
        copy = make()
        try:
            _, info = copy.reset()
        finally:
            copy.close()
        return info if isinstance(info, dict) else {}

    nvec = tuple(coding.nvec) if coding.categorical else None
    return resolve_mask(mode, key, env.observation_space, nvec, probe, where)
