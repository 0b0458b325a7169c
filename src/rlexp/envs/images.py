"""Image observations of the Gymnasium-shaped backends (DESIGN #47, docs/envs.md "Images").

- **Detection** (``image_layout``): a uint8 ``Box`` of rank 3 is an image, HWC when its last
  dimension is 1, 3 or 4 and its first is not, else CHW; rank 4 is stacked frames, ``[N, H, W, C]``
  or ``[N, C, H, W]`` by the same rule on the last three dimensions, folded into ``[N*C, H, W]``;
  a key ``env.image_keys`` names is an image too (uint8 of rank 2 to 4; rank 2 is one grey channel).
  Any other uint8 ``Box`` of rank >= 3 is refused in one line naming the key and the shape.
- **What the policy sees**: one uint8 ``[C, H, W]`` array per image (``image_encoder``), at the
  observation TensorDict key ``image_key_of(key)`` (``"pixels"`` at the root); never a float copy.
- **Batches** (``ObsBatch``): a batch of observations with images is a dict of numpy arrays, first
  axis the copy (``"vector"`` float32 [n, dim] unless dim is 0, each image uint8 [n, C, H, W]),
  indexed and assigned like the flat [n, dim] array it replaces.
- **Frame stacking** (``FrameStack``, ``env.frame_stack=N``): a Gymnasium wrapper stacking each
  image's last N frames along a new first axis (newest last; a reset fills the stack with its
  first frame), so the layout sees stacked frames and folds them into channels.

No torch here: the ``gymnasium_async`` workers import this module.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

#: The TensorDict key of an image at the root of the observation.
ROOT_IMAGE_KEY = "pixels"
#: The TensorDict key of the flat float32 vector of the non-image parts.
VECTOR_KEY = "vector"
#: The action mask's entry (``masks.MASK_KEY``; not imported: masks.py imports nothing of ours).
MASK_ENTRY = "action_mask"
#: Channel counts a last dimension may have for an image to read as HWC.
CHANNELS = (1, 3, 4)


def image_key_of(key: str) -> str:
    """The observation TensorDict key of the image at space path ``key``."""
    return key.replace("/", ".") if key else ROOT_IMAGE_KEY


def _hwc(shape: Sequence[int]) -> bool:
    return shape[-1] in CHANNELS and shape[-3] not in CHANNELS


def image_layout(
    shape: tuple[int, ...], dtype: Any, named: bool, at: str, where: str, refused: type
) -> tuple[tuple[int, int, int], str] | None:
    """``(the CHW shape the policy sees, the source layout)`` when a Box of ``shape`` and ``dtype``
    is an image, None when it is not (a vector part); ``refused`` (one line naming ``at`` and the
    shape) for a Box that is an image in no layout rlexp reads. ``named``: ``env.image_keys``
    names it."""
    uint8 = np.dtype(dtype) == np.uint8
    rank = len(shape)
    if not named and (not uint8 or rank < 3):
        return None
    box = f"Box{tuple(shape)} {np.dtype(dtype)}"
    if not uint8:
        raise refused(
            f"{where}: env.image_keys names the observation{at}, a {box}; images must be uint8 "
            "(0..255): drop it from env.image_keys or have the env give uint8 pixels"
        )
    if rank == 2 and named:
        return (1, *shape), "hw"
    if rank == 3:
        h, w, c = shape if _hwc(shape) else (shape[1], shape[2], shape[0])
        return (c, h, w), ("hwc" if _hwc(shape) else "chw")
    if rank == 4:
        n = shape[0]
        h, w, c = shape[1:] if _hwc(shape) else (shape[2], shape[3], shape[1])
        return (n * c, h, w), ("stack_hwc" if _hwc(shape) else "stack_chw")
    raise refused(
        f"{where}: the observation{at} is an image in an unsupported layout ({box}, rank {rank}); "
        "rlexp reads uint8 images as [H, W, C] or [C, H, W], stacked frames as [N, H, W, C] or "
        "[N, C, H, W] (env.image_keys may also name a [H, W] one)"
    )


def image_encoder(source: str, chw: tuple[int, int, int]) -> Callable[[Any], np.ndarray]:
    """The function giving an image leaf (any leading batch dimensions) as uint8 ``[..., C, H, W]``
    (a view where the env's layout is CHW already)."""
    c, h, w = chw
    if source == "hw":
        return lambda x: np.asarray(x, dtype=np.uint8)[..., None, :, :]
    if source == "hwc":
        return lambda x: np.moveaxis(np.asarray(x, dtype=np.uint8), -1, -3)
    if source == "chw":
        return lambda x: np.asarray(x, dtype=np.uint8)
    if source == "stack_hwc":

        def stack_hwc(x: Any) -> np.ndarray:
            x = np.moveaxis(np.asarray(x, dtype=np.uint8), -1, -3)  # [..., N, C, H, W]
            return x.reshape(*x.shape[:-4], c, h, w)

        return stack_hwc
    return lambda x: np.asarray(x, dtype=np.uint8).reshape(*np.shape(x)[:-4], c, h, w)


class ObsBatch:
    """Observations with images, batched: one numpy array per TensorDict key, first axis the copy.
    Indexing (an int, a slice, an index or mask array) gives the selected copies (views where numpy
    gives views); assigning takes an ``ObsBatch`` or a mapping of the same keys."""

    __slots__ = ("arrays",)

    def __init__(self, arrays: dict[str, np.ndarray]) -> None:
        self.arrays = arrays

    def __getitem__(self, idx: Any) -> ObsBatch:
        return ObsBatch({k: v[idx] for k, v in self.arrays.items()})

    def __setitem__(self, idx: Any, value: ObsBatch | Mapping[str, Any]) -> None:
        source = value.arrays if isinstance(value, ObsBatch) else value
        for k, v in self.arrays.items():
            v[idx] = source[k]

    def __len__(self) -> int:
        return len(next(iter(self.arrays.values())))

    def copy(self) -> ObsBatch:
        return ObsBatch({k: v.copy() for k, v in self.arrays.items()})


def empty_obs(layout: Any, n: int) -> np.ndarray | ObsBatch:
    """Zeros for ``n`` copies' observations: float32 [n, dim], or an ``ObsBatch`` with images."""
    if not layout.structured:
        return np.zeros((n, layout.dim), dtype=np.float32)
    arrays = {VECTOR_KEY: np.zeros((n, layout.dim), dtype=np.float32)} if layout.dim else {}
    for part in layout.images:
        arrays[part.image_key] = np.zeros((n, *part.shape), dtype=np.uint8)
    if layout.mask is not None:  # every action valid until the env says otherwise
        arrays[MASK_ENTRY] = np.ones((n, layout.mask.width), dtype=bool)
    return ObsBatch(arrays)


def stack_obs(layout: Any, rows: Sequence[Any]) -> np.ndarray | ObsBatch:
    """Per-copy encoded observations (``ObsLayout.encode``) as one batch."""
    if not layout.structured:
        return np.stack(rows).astype(np.float32)
    rows = [row.arrays if isinstance(row, ObsBatch) else row for row in rows]
    return ObsBatch({k: np.stack([row[k] for row in rows]) for k in rows[0]})


def encode_rows(layout: Any, obs: Any) -> np.ndarray | ObsBatch:
    """A vector env's raw batch whose leaves are batched arrays [n, ...] in a Dict or Tuple
    (EnvPool's MiniGrid: an image, a direction and a mission; DMC: named vectors), which
    ``ObsLayout.encode_batch`` cannot take in one piece: each copy's observation encoded as a
    single env's is (``ObsLayout.encode``), stacked."""
    n = len(_first_leaf(obs))
    return stack_obs(layout, [layout.encode(_row(obs, i)) for i in range(n)])


def _row(obs: Any, i: int) -> Any:
    if isinstance(obs, Mapping):
        return {k: _row(v, i) for k, v in obs.items()}
    if isinstance(obs, tuple | list):
        return tuple(_row(v, i) for v in obs)
    return obs[i]


def _first_leaf(obs: Any) -> Any:
    while isinstance(obs, Mapping | tuple | list):
        obs = next(iter(obs.values())) if isinstance(obs, Mapping) else obs[0]
    return obs


def as_obs(layout: Any, batch: Any) -> np.ndarray | ObsBatch:
    """A vector env's batched observations (already encoded per copy, e.g. shared memory of the
    workers) as an owned batch: float32 [n, dim], or an ``ObsBatch`` copied out of ``batch``."""
    if not layout.structured:
        return np.array(batch, dtype=np.float32)
    return ObsBatch({k: np.array(batch[k]) for k in empty_obs(layout, 0).arrays})


def obs_state(obs: np.ndarray | ObsBatch) -> Any:
    """A batch as plain data for a checkpoint (a dict of arrays for an ``ObsBatch``)."""
    return {k: v.copy() for k, v in obs.arrays.items()} if isinstance(obs, ObsBatch) else obs.copy()


def obs_from_state(state: Any) -> np.ndarray | ObsBatch:
    """``obs_state``'s data as a batch again (float32 vectors, uint8 images kept)."""
    if isinstance(state, Mapping):
        return ObsBatch({k: np.array(v) for k, v in state.items()})
    return np.array(state, dtype=np.float32)


def encoded_space(layout: Any) -> spaces.Space:
    """The space of ``layout``'s encoded observation (what a worker puts in shared memory): a flat
    float32 Box, or a Dict of ``vector`` and uint8 CHW images."""
    vector = spaces.Box(-np.inf, np.inf, (layout.dim,), np.float32)
    if not layout.structured:
        return vector
    entries: dict[str, spaces.Space] = {VECTOR_KEY: vector} if layout.dim else {}
    for part in layout.images:
        entries[part.image_key] = spaces.Box(0, 255, part.shape, np.uint8)
    if layout.mask is not None:
        entries[MASK_ENTRY] = spaces.Box(0, 1, (layout.mask.width,), np.bool_)
    return spaces.Dict(entries)


class FrameStack(gym.ObservationWrapper):
    """``env.frame_stack=N``: each image leaf (space paths ``paths``) as its last ``N`` frames,
    stacked along a new first axis (a rank-4 leaf: concatenated along its first axis), newest
    last; a reset fills the stack with the reset's frame. Vector leaves pass as they are."""

    def __init__(self, env: gym.Env, n: int, paths: Sequence[str]) -> None:
        super().__init__(env)
        self.n, self.paths = int(n), tuple(paths)
        self._frames: dict[str, deque] = {p: deque(maxlen=self.n) for p in self.paths}
        self.observation_space = _map_leaves(env.observation_space, self.paths, self._stack_space)

    def _stack_space(self, sp: spaces.Box) -> spaces.Box:
        low = self._join([np.asarray(sp.low)] * self.n)
        high = self._join([np.asarray(sp.high)] * self.n)
        return spaces.Box(low=low, high=high, dtype=sp.dtype)

    def _join(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        return np.concatenate(frames) if frames[0].ndim == 4 else np.stack(frames)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        for path in self.paths:
            self._frames[path].extend([np.array(_get(obs, path))] * self.n)
        return _map_leaves(obs, self.paths, self._current), info

    def observation(self, obs: Any) -> Any:
        return _map_leaves(obs, self.paths, self._push)

    def _push(self, frame: Any, path: str) -> np.ndarray:
        self._frames[path].append(np.array(frame))  # (a copy: an env may reuse its buffer)
        return self._current(frame, path)

    def _current(self, frame: Any, path: str) -> np.ndarray:
        return self._join(list(self._frames[path]))


def _get(obs: Any, path: str) -> Any:
    for name in path.split("/") if path else ():
        obs = obs[int(name)] if isinstance(obs, tuple | list) else obs[name]
    return obs


def _map_leaves(obs: Any, paths: Sequence[str], fn: Callable, prefix: str = "") -> Any:
    """``obs`` (a space or an observation) with the leaves at ``paths`` replaced by ``fn(leaf)``
    (observations: ``fn(leaf, path)``)."""
    is_space = isinstance(obs, spaces.Space)
    if prefix in paths:
        return fn(obs) if is_space else fn(obs, prefix)
    join = (lambda k: f"{prefix}/{k}") if prefix else str
    if isinstance(obs, spaces.Dict | Mapping):
        items = obs.spaces.items() if is_space else obs.items()
        out = {k: _map_leaves(v, paths, fn, join(k)) for k, v in items}
        return spaces.Dict(out) if is_space else out
    if isinstance(obs, spaces.Tuple | tuple):
        subs = obs.spaces if is_space else obs
        out = tuple(_map_leaves(v, paths, fn, join(i)) for i, v in enumerate(subs))
        return spaces.Tuple(out) if is_space else out
    return obs
