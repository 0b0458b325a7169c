"""The env's observation as the loop meets it: one flat float32 tensor ``[..., dim]``, or (images,
issue #47) a TensorDict of ``"vector"`` (float32 ``[..., dim]``, absent when dim is 0) and uint8
``[..., C, H, W]`` image entries. The few operations the collector, the update, the checkpoint and
the events need on either, written once; images stay uint8 in all of them (no float copy).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

Observation = torch.Tensor | TensorDictBase

#: the float entry of a structured observation (every non-image part, every group)
VECTOR = "vector"


def structured(obs: Any) -> bool:
    """Whether ``obs`` is a TensorDict observation (vector and images), not one flat tensor."""
    return isinstance(obs, TensorDictBase)


def vector_of(obs: Observation) -> torch.Tensor | None:
    """The flat float32 vector of the observation (the normaliser's input); None where it has
    none (images only)."""
    if isinstance(obs, TensorDictBase):
        return obs.get(VECTOR, None)
    return obs


def with_vector(obs: Observation, vector: torch.Tensor) -> Observation:
    """``obs`` with its vector replaced (a shallow copy of a TensorDict: the images are shared)."""
    if isinstance(obs, TensorDictBase):
        out = obs.copy()
        out.set(VECTOR, vector)
        return out
    return vector


def leaves(obs: Observation) -> list[torch.Tensor]:
    """The observation's tensors: itself, or each entry of the TensorDict (sorted keys)."""
    if isinstance(obs, TensorDictBase):
        return [obs.get(k) for k in sorted(obs.keys(True, True), key=str)]
    return [obs]


def all_finite(obs: Observation) -> bool:
    """No NaN or Inf in the observation's float entries (uint8 images are always finite)."""
    return all(bool(torch.isfinite(t).all()) for t in leaves(obs) if t.is_floating_point())


def equal_rows(a: Observation, b: Observation, batch_dims: int) -> torch.Tensor:
    """Per sample (the first ``batch_dims`` dims), whether ``a`` and ``b`` are bit-equal in every
    entry: bool ``[*batch]`` (a byte per element compared, never a float copy)."""
    pairs = zip(leaves(a), leaves(b), strict=True)
    same = [(_rows(x, batch_dims) == _rows(y, batch_dims)).all(-1) for x, y in pairs]
    return functools.reduce(torch.logical_and, same)


def _rows(x: torch.Tensor, batch_dims: int) -> torch.Tensor:
    """``x`` as one row per sample; a uint8 row (an image) seen as int64 words where its memory
    allows (a view: equal bytes are equal words, so the verdict is the same with 8x fewer
    comparisons; 8 x 128 frames of 84x84x4: ~40 ms -> 4-8 ms of each update's GAE here)."""
    rows = x.flatten(batch_dims)
    if rows.dtype == torch.uint8 and rows.shape[-1] % 8 == 0:
        try:
            return rows.view(torch.int64)
        except RuntimeError:  # strides or offset not multiples of 8 bytes: compared byte by byte
            pass
    return rows


def next_is_following(obs: Observation, next_obs: Observation, batch_dims: int) -> torch.Tensor:
    """Of a rollout ``[*B, T]`` (time the last batch dim): whether each step's next observation
    is bit-equal to the following step's observation (no reset between), bool ``[*B, T-1]``."""
    lead = (slice(None),) * (batch_dims - 1)
    return equal_rows(next_obs[(*lead, slice(-1))], obs[(*lead, slice(1, None))], batch_dims)


def in_chunks(
    fn: Callable[[TensorDictBase], torch.Tensor], rows: int
) -> Callable[[TensorDictBase], torch.Tensor]:
    """``fn`` (a network) over a TensorDict observation of any batch shape, ``rows`` samples at a
    time: the encoder's float copy of the uint8 images is a chunk's, never the whole rollout's."""
    step = max(1, int(rows))

    def run(obs: TensorDictBase) -> torch.Tensor:
        flat = obs.reshape(-1)
        if flat.shape[0] <= step:
            return fn(obs)
        out = torch.cat([fn(flat[i : i + step]) for i in range(0, flat.shape[0], step)])
        return out.reshape(*obs.batch_size, *out.shape[1:])

    return run


def to_plain(obs: Observation | None) -> Any:
    """A checkpoint's form (``torch.load(weights_only=True)``): the tensor, or a dict of tensors."""
    if isinstance(obs, TensorDictBase):
        return obs.to_dict()
    return obs


def from_plain(value: Any) -> Observation | None:
    """``to_plain``'s inverse: a dict of tensors becomes the TensorDict again (its batch size:
    the leading dims the entries share, the per-sample dims dropped)."""
    if not isinstance(value, Mapping):
        return value
    td = TensorDict(dict(value), batch_size=[])
    vector = td.get(VECTOR, None)
    if vector is None:  # an action mask [..., width] has the batch dims the vector would have
        vector = td.get("action_mask", None)
    if vector is not None:
        batch = vector.shape[:-1]
    else:  # images only: [..., C, H, W]
        batch = next(iter(leaves(td))).shape[:-3]
    return TensorDict(dict(value), batch_size=batch)
