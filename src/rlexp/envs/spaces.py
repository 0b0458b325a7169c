"""Gymnasium spaces as what rlexp's policies see: one flat float32 observation vector and one action
tensor, with the layout written down so that checkpoints and exported files can never silently
disagree with the env.

Observations (``ObsLayout``): ``Box`` (flattened in C order, cast to float32), ``Discrete`` (one-hot),
``MultiBinary`` (0/1 floats), ``MultiDiscrete`` (one one-hot per component), and ``Dict`` / ``Tuple``
of those, nested to any depth. Containers are flattened depth-first: a ``Dict``'s keys in sorted
order (``str`` order of the key, whatever order the space lists them in), a ``Tuple``'s entries by
index; a part's key is its path joined with ``/`` (``"goal/position"``, ``"0"``). Images (a uint8
``Box`` of rank 3 or 4, or a key ``env.image_keys`` names; ``images.py``) are not in the vector:
with images the observation is a TensorDict of ``"vector"`` (float32) and one uint8 ``[C, H, W]``
entry per image (``ObsLayout.encode``). ``Text``, ``Graph``, ``Sequence``, ``OneOf`` are refused.
``env.observation_indices`` keeps chosen entries of a ``Box`` observation (flattened in C order), in
the order given: the layout's one part is then a Box of that many values whose record names the
kept ``indices``, so a checkpoint or export made with other entries is refused.

Actions (``ActionCoding``): ``Box`` (a Gaussian head; actions clipped to the box), ``Discrete``,
``MultiDiscrete`` and ``MultiBinary`` (a categorical head per component). A categorical action is an
int64 vector ``[K]`` of component indices counted from 0 (``K = 1`` for ``Discrete``); ``decode``
adds each component's ``start`` and gives the env the shape and dtype its space has.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from gymnasium import spaces

from rlexp.envs.groups import group_rule
from rlexp.envs.images import (
    VECTOR_KEY,
    FrameStack,
    ObsBatch,
    encode_rows,
    image_encoder,
    image_key_of,
    image_layout,
)
from rlexp.envs.masks import MASK_KEY, MaskSpec, mask_encoder

#: What the two tables above say, for error messages and docs.
SUPPORTED_OBSERVATIONS = (
    "Box, Discrete, MultiBinary, MultiDiscrete, and Dict/Tuple of them (nested; flattened), "
    "uint8 images (HWC, CHW, stacked frames)"
)
SUPPORTED_ACTIONS = "Box (Gaussian), Discrete, MultiDiscrete, MultiBinary (categorical)"
#: How containers are flattened (recorded in checkpoints and export metadata).
FLATTEN_ORDER = "depth-first; Dict keys sorted by str(key), Tuple entries by index"


class UnsupportedSpace(TypeError):
    """An observation or action space rlexp's MLP policies cannot take; the message is one line."""


@dataclass(frozen=True)
class ObsPart:
    """One leaf of the observation space and where it lands in the flat vector."""

    key: str  # path in the space ("" for a plain Box at the root)
    kind: str  # box | discrete | multi_binary | multi_discrete | image
    shape: tuple[int, ...]  # the space's own shape (image: the uint8 CHW shape the policy sees)
    offset: int  # first index in the flat vector (image: -1, not in it)
    size: int  # width in the flat vector (image: 0)
    nvec: tuple[int, ...] = ()  # discrete / multi_discrete: number of values per component
    start: tuple[int, ...] = ()  # discrete / multi_discrete: the smallest value per component
    group: str = "policy"  # observation group (policy, critic, ...): what a network may select
    image_key: str = ""  # image: its entry in the observation TensorDict ("pixels" at the root)
    source_layout: str = ""  # image: how the env gave it (hwc | chw | stack_hwc | ...)
    #: box: the entries of the env's flat Box kept, in this order (env.observation_indices; empty:
    #: every entry, as the env gives them)
    indices: tuple[int, ...] = ()

    def record(self) -> dict[str, Any]:
        out = {
            "key": self.key,
            "kind": self.kind,
            "shape": list(self.shape),
            "offset": self.offset,
            "size": self.size,
        }
        if self.nvec:
            out["nvec"], out["start"] = list(self.nvec), list(self.start)
        if self.group != "policy":  # written only when not the default: old records compare equal
            out["group"] = self.group
        if self.kind == "image":
            out["image_key"], out["source_layout"] = self.image_key, self.source_layout
        if self.indices:  # written only when set: old records compare equal
            out["indices"] = list(self.indices)
        return out


@dataclass(frozen=True)
class ObsLayout:
    """How an observation becomes the flat float32 vector the policy reads."""

    space_name: str
    parts: tuple[ObsPart, ...]
    dim: int
    #: a 1-D float Box at the root: the observation is the vector (the fast path)
    plain: bool = False
    _encoders: tuple[Callable[[Any], np.ndarray], ...] = field(default=(), compare=False)
    #: env.frame_stack: images are the env's last N frames (1: as the env gives them)
    frame_stack: int = 1
    #: the action mask (``masks.py``): the observation's ``action_mask`` entry (None: no mask)
    mask: MaskSpec | None = None
    _mask_encoder: Callable[[Any], np.ndarray] | None = field(default=None, compare=False)

    @property
    def images(self) -> tuple[ObsPart, ...]:
        """The image parts (uint8 entries of the observation TensorDict, not in the flat vector)."""
        return tuple(p for p in self.parts if p.kind == "image")

    @property
    def structured(self) -> bool:
        """Whether the observation is a TensorDict (``vector``, images, the action mask), not one
        flat vector."""
        return bool(self.images) or self.mask is not None

    def encode_mask(self, obs: Any, info: Any) -> np.ndarray:
        """The action mask of one copy's observation or info, bool [width]."""
        mask = self.mask
        if mask.source == "info":
            raw = info.get(mask.key) if isinstance(info, dict) else None
        else:
            raw = _leaf(obs, mask.key)
        return self._mask_encoder(raw)

    def flatten(self, obs: Any) -> np.ndarray:
        """The observation's non-image parts as a float32 vector [dim]."""
        if self.plain:
            return np.asarray(obs, dtype=np.float32).reshape(-1)
        out = np.empty(self.dim, dtype=np.float32)
        self.flatten_into(out, obs)
        return out

    def flatten_into(self, out: np.ndarray, obs: Any) -> None:
        """Write the flattened observation into ``out`` [dim] (no allocation for a plain Box)."""
        if self.plain:
            out[:] = obs
            return
        for part, encode in zip(self.parts, self._encoders, strict=True):
            if part.kind != "image":
                out[part.offset : part.offset + part.size] = encode(_leaf(obs, part.key))

    def encode(self, obs: Any, info: Any = None) -> np.ndarray | dict[str, np.ndarray]:
        """The observation as the env emits it for one copy: the flat float32 vector [dim], or
        with images or a mask a dict of ``"vector"`` (unless dim is 0), uint8 ``[C, H, W]`` per
        image and the bool ``action_mask`` (from ``obs`` or the step's ``info``)."""
        if not self.structured:
            return self.flatten(obs)
        out = {VECTOR_KEY: self.flatten(obs)} if self.dim else {}
        for part, encode in zip(self.parts, self._encoders, strict=True):
            if part.kind == "image":
                out[part.image_key] = encode(_leaf(obs, part.key))
        if self.mask is not None:
            out[MASK_KEY] = self.encode_mask(obs, info)
        return out

    def encode_into(self, out: np.ndarray | ObsBatch, obs: Any, info: Any = None) -> None:
        """``encode`` written into one copy's row of a batch (``out``: a [dim] view or an
        ``ObsBatch`` row)."""
        if not isinstance(out, ObsBatch):
            self.flatten_into(out, obs)
            return
        arrays = out.arrays
        if self.dim:
            self.flatten_into(arrays[VECTOR_KEY], obs)
        for part, encode in zip(self.parts, self._encoders, strict=True):
            if part.kind == "image":
                arrays[part.image_key][...] = encode(_leaf(obs, part.key))
        if self.mask is not None:
            arrays[MASK_KEY][...] = self.encode_mask(obs, info)

    @property
    def indices(self) -> tuple[int, ...]:
        """``env.observation_indices``: the env's flat Box entries kept, in order (empty: all)."""
        return self.parts[0].indices if len(self.parts) == 1 else ()

    @property
    def batchable(self) -> bool:
        """Whether ``encode_batch`` takes this layout in one piece: a plain Box (entries kept or
        not), or one image at the root (else it encodes copy by copy)."""
        return (
            self.plain
            or bool(self.indices)
            or (len(self.parts) == 1 and self.parts[0].kind == "image")
        )

    def encode_batch(self, obs: Any) -> np.ndarray | ObsBatch:
        """A vector env's raw batch [n, ...] as the env emits it: float32 [n, dim], or an
        ``ObsBatch`` of the uint8 [n, C, H, W] image (a new array either way); other layouts (a
        Dict or Tuple of batched leaves) copy by copy (``images.encode_rows``)."""
        if not self.batchable:
            return encode_rows(self, obs)
        if self.plain:
            return np.asarray(obs).astype(np.float32)
        part = self.parts[0]
        if part.indices:
            flat = np.asarray(obs).reshape(len(obs), -1)
            return flat[:, list(part.indices)].astype(np.float32)
        return ObsBatch({part.image_key: np.array(self._encoders[0](obs), order="C")})

    def record(self) -> dict[str, Any]:
        """Plain data for checkpoints and export metadata (compared on load)."""
        out = {
            "space": self.space_name,
            "dim": self.dim,
            "order": FLATTEN_ORDER,
            "parts": [p.record() for p in self.parts],
        }
        if self.frame_stack > 1:  # the images are the env's last N frames: a deployment stacks too
            out["frame_stack"] = self.frame_stack
        if self.mask is not None:  # (absent without a mask: old records compare equal)
            out["action_mask"] = self.mask.record()
        return out


def _leaf(obs: Any, key: str) -> Any:
    if not key:
        return obs
    for name in key.split("/"):
        obs = obs[int(name)] if isinstance(obs, tuple | list) else obs[_dict_key(obs, name)]
    return obs


def _dict_key(obs: Any, name: str) -> Any:
    if name in obs:
        return name
    for k in obs:  # a non-str key (Gymnasium allows any hashable): matched by str()
        if str(k) == name:
            return k
    raise KeyError(f"observation has no key {name!r} (its keys: {sorted(map(str, obs))})")


def _one_hot(n: int, start: int) -> Callable[[Any], np.ndarray]:
    eye = np.eye(n, dtype=np.float32)
    return lambda x: eye[int(x) - start]


def _multi_one_hot(nvec: np.ndarray, start: np.ndarray) -> Callable[[Any], np.ndarray]:
    offsets = np.concatenate([[0], np.cumsum(nvec)[:-1]]).astype(np.int64)
    total = int(nvec.sum())

    def encode(x: Any) -> np.ndarray:
        out = np.zeros(total, dtype=np.float32)
        out[offsets + (np.asarray(x, dtype=np.int64).reshape(-1) - start)] = 1.0
        return out

    return encode


def _box(x: Any) -> np.ndarray:
    return np.asarray(x, dtype=np.float32).reshape(-1)


def _describe(space: spaces.Space) -> str:
    text = repr(space)
    return text if len(text) <= 80 else text[:77] + "..."


def obs_layout(
    space: spaces.Space,
    where: str,
    image_keys: Sequence[str] = (),
    frame_stack: int = 1,
    mask: MaskSpec | None = None,
    indices: Sequence[int] = (),
) -> ObsLayout:
    """The layout of ``space``; ``UnsupportedSpace`` naming the part that cannot be flattened
    (``where``: the config key and value the env came from, for the message). ``image_keys``:
    keys ``env.image_keys`` names as images (a part's key, or its TensorDict key); ``frame_stack``
    is recorded (``space`` is the stacked one already: ``images.FrameStack``); ``mask``: the action
    mask (``masks.resolve_mask``; from the observation: that key is not a part of the vector);
    ``indices``: ``env.observation_indices``, the entries of a Box ``space`` kept (in this order)."""
    if indices:
        return _kept_layout(space, where, tuple(int(i) for i in indices), mask)
    parts: list[ObsPart] = []
    encoders: list[Callable[[Any], np.ndarray]] = []
    named = set(image_keys)
    seen: set[str] = set()  # Box keys and their TensorDict keys (what image_keys may name)
    boxes: list[str] = []

    def visit(sp: spaces.Space, key: str) -> None:
        offset = sum(p.size for p in parts)
        at = f" at key {key!r}" if key else ""
        if mask is not None and mask.source == "observation" and key == mask.key:
            return  # the action mask: the observation's action_mask entry, not the vector
        if isinstance(sp, spaces.Dict):
            for k in sorted(sp.spaces, key=str):
                visit(sp.spaces[k], f"{key}/{k}" if key else str(k))
        elif isinstance(sp, spaces.Tuple):
            for i, sub in enumerate(sp.spaces):
                visit(sub, f"{key}/{i}" if key else str(i))
        elif isinstance(sp, spaces.Box):
            image_key = image_key_of(key)
            is_named = bool(named & {key, image_key})
            seen.update({key, image_key})
            boxes.append(key or image_key)
            image = image_layout(tuple(sp.shape), sp.dtype, is_named, at, where, UnsupportedSpace)
            if image is not None:
                chw, source = image
                if image_key == VECTOR_KEY:
                    raise UnsupportedSpace(
                        f"{where}: the image at key {key!r} would be the observation entry "
                        f"{VECTOR_KEY!r}, which holds the flat vector; rename the env's key"
                    )
                parts.append(ObsPart(key, "image", chw, -1, 0, image_key=image_key,
                                     source_layout=source))  # fmt: skip
                encoders.append(image_encoder(source, chw))
                return
            size = int(np.prod(sp.shape))
            parts.append(ObsPart(key, "box", tuple(sp.shape), offset, size))
            encoders.append(_box)
        elif isinstance(sp, spaces.Discrete):
            n, start = int(sp.n), int(sp.start)
            parts.append(ObsPart(key, "discrete", (), offset, n, (n,), (start,)))
            encoders.append(_one_hot(n, start))
        elif isinstance(sp, spaces.MultiBinary):
            size = int(np.prod(sp.shape))
            parts.append(ObsPart(key, "multi_binary", tuple(sp.shape), offset, size))
            encoders.append(_box)
        elif isinstance(sp, spaces.MultiDiscrete):
            nvec = np.asarray(sp.nvec, dtype=np.int64).reshape(-1)
            start = np.asarray(sp.start, dtype=np.int64).reshape(-1)
            nv, st = tuple(int(v) for v in nvec), tuple(int(v) for v in start)
            parts.append(
                ObsPart(key, "multi_discrete", tuple(sp.shape), offset, int(nvec.sum()), nv, st)
            )
            encoders.append(_multi_one_hot(nvec, start))
        else:
            raise UnsupportedSpace(
                f"{where}: the observation space{at} is {type(sp).__name__} "
                f"({_describe(sp)}); rlexp takes {SUPPORTED_OBSERVATIONS}"
            )

    visit(space, "")
    if isinstance(space, spaces.Dict):  # top-level keys as groups (groups.py: Isaac Lab's Dicts)
        group = group_rule(str(k) for k in space.spaces)
        parts = [replace(p, group=group(p.key.split("/")[0])) for p in parts]
    unknown = sorted(named - seen)
    if unknown:
        raise UnsupportedSpace(
            f"{where}: env.image_keys={sorted(named)} names {unknown}, which the observation does "
            f"not have (its Box keys: {boxes}; an image at the root is {image_key_of('')!r})"
        )
    if not parts:
        raise UnsupportedSpace(f"{where}: the observation space {_describe(space)} is empty")
    dim = sum(p.size for p in parts)
    plain = (
        isinstance(space, spaces.Box)
        and len(space.shape) == 1
        and np.issubdtype(np.dtype(space.dtype), np.floating)
        and mask is None
    )
    stack = max(1, int(frame_stack))
    encode_mask = None if mask is None else mask_encoder(mask, where)
    return ObsLayout(
        type(space).__name__, tuple(parts), dim, plain, tuple(encoders), stack, mask, encode_mask
    )


def _kept_layout(
    space: spaces.Space, where: str, indices: tuple[int, ...], mask: MaskSpec | None = None
) -> ObsLayout:
    """``env.observation_indices``: the layout of the entries ``indices`` of the Box ``space``
    (flattened in C order; an image or any other space is refused in one line)."""
    what = f"env.observation_indices={list(indices)}"
    if not isinstance(space, spaces.Box) or obs_layout(space, where).images:
        kind = "an image" if isinstance(space, spaces.Box) else type(space).__name__
        raise UnsupportedSpace(
            f"{what} keeps entries of a Box observation, and {where}'s observation is {kind} "
            f"({_describe(space)}); leave env.observation_indices empty"
        )
    width = int(np.prod(space.shape))
    wrong = [i for i in indices if not 0 <= i < width]
    if wrong:
        raise UnsupportedSpace(
            f"{what}: {wrong[0]} is not an entry of {where}'s observation, which has {width} "
            f"values ({_describe(space)}); use indices 0 to {width - 1}"
        )
    keep = np.asarray(indices, dtype=np.int64)
    part = ObsPart("", "box", (len(indices),), 0, len(indices), indices=indices)

    def encode(x: Any) -> np.ndarray:
        return np.asarray(x, dtype=np.float32).reshape(-1)[keep]

    encode_mask = None if mask is None else mask_encoder(mask, where)
    return ObsLayout(
        type(space).__name__, (part,), len(indices), False, (encode,), 1, mask, encode_mask
    )


@dataclass(frozen=True)
class ActionCoding:
    """What the policy outputs for an action space and how it becomes the env's action."""

    kind: str  # box | discrete | multi_discrete | multi_binary
    shape: tuple[int, ...]  # the space's shape
    dim: int  # box: number of action dims; categorical: number of components K
    nvec: tuple[int, ...] = ()  # categorical: values per component
    start: tuple[int, ...] = ()  # categorical: the smallest value per component
    low: tuple[float, ...] = ()  # box: bounds, flattened
    high: tuple[float, ...] = ()
    dtype: str = "float32"  # the space's dtype

    @property
    def categorical(self) -> bool:
        return self.kind != "box"

    def decode(self, action: np.ndarray) -> Any:
        """One env's policy output (box: float [dim], clipped; categorical: int [K]) as the env's
        action."""
        if self.kind == "discrete":
            return int(action[0]) + self.start[0]
        if self.kind == "box":
            return action.reshape(self.shape) if len(self.shape) != 1 else action
        return (np.asarray(action) + np.asarray(self.start)).reshape(self.shape).astype(self.dtype)

    def decode_batch(self, actions: np.ndarray) -> np.ndarray:
        """``decode`` for every copy at once (box: float [n, dim], clipped; categorical: int
        [n, K]): the batched action a vector env (AsyncVectorEnv, EnvPool) takes."""
        n = actions.shape[0]
        if self.kind == "box":
            return actions if len(self.shape) == 1 else actions.reshape(n, *self.shape)
        if self.kind == "discrete":
            return (actions[:, 0] + self.start[0]).astype(self.dtype)
        shifted = np.asarray(actions) + np.asarray(self.start)
        return shifted.reshape(n, *self.shape).astype(self.dtype)

    def record(self) -> dict[str, Any]:
        """Plain data for checkpoints and export metadata."""
        out: dict[str, Any] = {
            "kind": self.kind,
            "shape": list(self.shape),
            "dim": self.dim,
            "dtype": self.dtype,
        }
        if self.categorical:
            out["nvec"], out["start"] = list(self.nvec), list(self.start)
        else:
            out["low"], out["high"] = list(self.low), list(self.high)
        return out


def action_coding(space: spaces.Space, where: str) -> ActionCoding:
    """The coding of ``space``; ``UnsupportedSpace`` for anything else (one line)."""
    dtype = str(np.dtype(space.dtype)) if space.dtype is not None else "int64"
    if isinstance(space, spaces.Box):
        low = np.asarray(space.low, dtype=np.float64).reshape(-1)
        high = np.asarray(space.high, dtype=np.float64).reshape(-1)
        return ActionCoding(
            "box",
            tuple(space.shape),
            int(low.size),
            low=tuple(float(v) for v in low),
            high=tuple(float(v) for v in high),
            dtype=dtype,
        )
    if isinstance(space, spaces.Discrete):
        return ActionCoding("discrete", (), 1, (int(space.n),), (int(space.start),), dtype=dtype)
    if isinstance(space, spaces.MultiDiscrete):
        nvec = tuple(int(v) for v in np.asarray(space.nvec).reshape(-1))
        start = tuple(int(v) for v in np.asarray(space.start).reshape(-1))
        return ActionCoding(
            "multi_discrete", tuple(space.shape), len(nvec), nvec, start, dtype=dtype
        )
    if isinstance(space, spaces.MultiBinary):
        k = int(np.prod(space.shape))
        return ActionCoding("multi_binary", tuple(space.shape), k, (2,) * k, (0,) * k, dtype=dtype)
    raise UnsupportedSpace(
        f"{where}: the action space is {type(space).__name__} ({_describe(space)}); rlexp's "
        f"policies take {SUPPORTED_ACTIONS}"
    )


def frame_stacked(env: Any, n: int, image_keys: Sequence[str], where: str) -> Any:
    """``env.frame_stack=n``: ``env`` behind ``images.FrameStack`` over its image leaves (``n`` 0
    or 1: ``env`` itself); ``UnsupportedSpace`` (one line) when it has no image to stack."""
    if n <= 1:
        return env
    images = obs_layout(env.observation_space, where, image_keys).images
    if not images:
        env.close()
        raise UnsupportedSpace(
            f"{where}: env.frame_stack={n} stacks image frames, and the observation "
            f"({_describe(env.observation_space)}) has no image; use env.frame_stack=0"
        )
    return FrameStack(env, n, [p.key for p in images])
