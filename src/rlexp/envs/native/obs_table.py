"""The native env's observation: the observation terms' outputs as one dict (``observe``), laid out
(``ObsTable``) as the flat float32 vector of every group and, for a camera term, uint8 images.

Each entry belongs to the group of the term that added it (``robot/qpos``, ``robot/qvel``,
``robot/qf``: ``policy``); a ``modify`` term keeps its entry's group (naming another is refused).
The vector holds the ``policy`` group's entries first, then each other group's, groups by name,
each group's entries with their keys sorted at every level: a task without groups keeps the layout
it always had. An entry of uint8 ``[N, H, W, C]`` (``camera_image``) is an image: not in the vector
but its own entry of the observation TensorDict (``image_key``: the name with ``/`` as ``.``),
``[N, C, H, W]`` (docs/envs.md "Observation groups").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from tensordict import TensorDict

from rlexp.envs.images import image_key_of
from rlexp.envs.native.terms import TERM_ERRORS, named_error
from rlexp.envs.spaces import ObsLayout, ObsPart

if TYPE_CHECKING:
    from rlexp.envs.native.state import SimState

ROBOT_OBSERVATIONS = ("robot/qpos", "robot/qvel", "robot/qf")  # every observation starts from these


def observe(env: SimState, terms: list) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Every entry (``[N, ...]``) the terms make, and each entry's group."""
    obs = {
        "robot/qpos": env.robot_qpos(),
        "robot/qvel": env.robot_qvel(),
        "robot/qf": env.robot_qf(),
    }
    groups = dict.fromkeys(obs, "policy")
    for key, func, mode, name, params, group in terms:
        if mode == "modify":
            if name not in obs:
                raise KeyError(
                    f"observations.{key}: mode 'modify' needs an existing entry {name!r}; have {sorted(obs)}"
                )
            if group != groups[name]:
                raise ValueError(
                    f"observations.{key}.group={group!r}, but the entry {name!r} it modifies is in "
                    f"group {groups[name]!r}; give it group: {groups[name]}"
                )
            try:
                obs[name] = func(env, obs[name], **params)
            except TERM_ERRORS as exc:
                raise named_error(exc, f"observations.{key}") from exc
        else:
            if name in obs:
                raise KeyError(
                    f"observations.{key}: mode 'add' but {name!r} already exists; use mode 'modify'"
                )
            try:
                obs[name] = func(env, **params)
            except TERM_ERRORS as exc:
                raise named_error(exc, f"observations.{key}") from exc
            groups[name] = group
    _no_group_collision(terms, groups)
    return obs, groups


def _no_group_collision(terms: list, groups: dict[str, str]) -> None:
    """One line when a group's name is also the key (or a key prefix) of an entry in another group:
    ``policy.*.observations`` selecting that name would mean both."""
    for key, _func, _mode, _name, _params, group in terms:
        clash = [n for n, g in groups.items() if g != group and (n + "/").startswith(group + "/")]
        if clash:
            raise ValueError(
                f"observations.{key}.group={group!r} is also the key of {clash[0]!r} (group "
                f"{groups[clash[0]]!r}): selecting {group!r} would mean both; name the group "
                f"otherwise (e.g. {group + '_group'!r})"
            )


def _is_image(value: np.ndarray) -> bool:
    return value.dtype == np.uint8 and value.ndim == 4


@dataclass(frozen=True)
class ObsTable:
    """Where each entry goes: ``entries`` (name, start, stop, shape) of the vector, ``images``
    (name, image_key, CHW shape), ``layout`` (what checkpoints record and networks select from)."""

    entries: tuple[tuple[str, int, int, tuple[int, ...]], ...]
    images: tuple[tuple[str, str, tuple[int, int, int]], ...]
    layout: ObsLayout

    @property
    def dim(self) -> int:
        return self.layout.dim

    def flatten(self, obs: dict[str, np.ndarray], n: int) -> np.ndarray:
        """The vector [N, dim] float32."""
        out = np.empty((n, self.dim), dtype=np.float32)
        for name, start, stop, _ in self.entries:
            out[:, start:stop] = obs[name].reshape(n, -1)
        return out

    def pixels(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Each image as uint8 [N, C, H, W] (contiguous), by its TensorDict key."""
        return {
            key: np.ascontiguousarray(obs[name].transpose(0, 3, 1, 2))
            for name, key, _ in self.images
        }

    def output(self, vector: np.ndarray, images: dict[str, np.ndarray], device: Any = None) -> Any:
        """What the env emits: the vector as a tensor, or (images) a TensorDict of ``vector`` and
        each image (DESIGN47 §1: ``vector`` left out when the vector is empty)."""
        if not self.images:
            return torch.from_numpy(vector)
        entries = {key: torch.from_numpy(img.copy()) for key, img in images.items()}
        if self.dim:
            entries["vector"] = torch.from_numpy(vector)
        return TensorDict(entries, batch_size=[vector.shape[0]], device=device)


def make_table(obs: dict[str, np.ndarray], groups: dict[str, str]) -> ObsTable:
    """The layout of ``obs`` (one build-time observation): the policy group first (module doc)."""

    def order(name: str) -> tuple:
        return (groups[name] != "policy", groups[name], tuple(name.split("/")))

    entries, images, parts, start = [], [], [], 0
    for name in sorted(obs, key=order):
        value = obs[name]
        if _is_image(value):
            h, w, c = (int(x) for x in value.shape[1:])
            key = image_key_of(name)
            images.append((name, key, (c, h, w)))
            parts.append(
                ObsPart(name, "image", (c, h, w), -1, 0, group=groups[name], image_key=key,
                        source_layout="hwc")
            )  # fmt: skip
            continue
        shape = tuple(int(x) for x in value.shape[1:])
        size = int(np.prod(shape))
        entries.append((name, start, start + size, shape))
        parts.append(ObsPart(name, "box", shape, start, size, group=groups[name]))
        start += size
    layout = ObsLayout("native", tuple(parts), start)
    return ObsTable(tuple(entries), tuple(images), layout)
