"""The TorchRL specs every rlexp env presents, whatever its backend: a flat float32 ``observation``
[n, obs_dim] (with images: a ``Composite`` of ``vector`` float32 [n, obs_dim] and one uint8
[n, C, H, W] entry per image), a ``Bounded`` float32 or ``MultiCategorical`` int64 action
[n, act_dim], a float32 reward [n, 1] and bool ``done`` / ``terminated`` / ``truncated`` [n, 1]."""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import Binary, Bounded, Categorical, Composite, MultiCategorical, Unbounded
from torchrl.envs import EnvBase

from rlexp.envs.images import VECTOR_KEY, ObsBatch
from rlexp.envs.masks import MASK_KEY
from rlexp.envs.spaces import ActionCoding, ObsLayout


def observation_spec(layout: ObsLayout | None, n: int, obs_dim: int, dev: torch.device):
    """The ``observation`` entry's spec: float32 [n, obs_dim], or a Composite with images."""
    vector = Unbounded(shape=(n, obs_dim), dtype=torch.float32, device=dev)
    if layout is None or not layout.structured:
        return vector
    entries = {VECTOR_KEY: vector} if obs_dim else {}
    for part in layout.images:
        shape = (n, *part.shape)
        entries[part.image_key] = Bounded(0, 255, shape=shape, dtype=torch.uint8, device=dev)
    if layout.mask is not None:  # bool [n, sum(nvec)]: which actions are valid (masks.py)
        width = layout.mask.width
        entries[MASK_KEY] = Binary(n=width, shape=(n, width), dtype=torch.bool, device=dev)
    return Composite(entries, shape=(n,), device=dev)


def obs_tensor(obs: np.ndarray | ObsBatch, n: int) -> torch.Tensor | TensorDict:
    """A batch of observations in numpy as the env's ``observation`` (sharing its memory): a
    tensor, or a TensorDict [n] of ``vector`` and the uint8 images."""
    if not isinstance(obs, ObsBatch):
        return torch.from_numpy(obs)
    arrays = {k: torch.from_numpy(v) for k, v in obs.arrays.items()}
    return TensorDict._new_unsafe(arrays, batch_size=torch.Size([n]))


def obs_numpy(obs: torch.Tensor | TensorDict) -> np.ndarray | ObsBatch:
    """``obs_tensor``'s inverse (CPU tensors; sharing their memory)."""
    if isinstance(obs, torch.Tensor):
        return obs.numpy()
    return ObsBatch({k: obs.get(k).numpy() for k in obs.keys()})


def set_specs(
    env: EnvBase, n: int, obs_dim: int, coding: ActionCoding, layout: ObsLayout | None = None
) -> None:
    """Give ``env`` (batch size [n], on its own device) rlexp's specs for ``coding``'s actions
    (``layout``: the observation's, for its images)."""
    dev, act_dim = env.device, coding.dim
    env.observation_spec = Composite(
        observation=observation_spec(layout, n, obs_dim, dev),
        shape=(n,),
        device=dev,
    )
    if coding.categorical:
        env.action_spec = MultiCategorical(
            nvec=list(coding.nvec), shape=(n, act_dim), dtype=torch.int64, device=dev
        )
    else:
        bound = lambda v: torch.as_tensor(v, dtype=torch.float32).expand(n, act_dim).clone()  # noqa: E731
        env.action_spec = Bounded(
            low=bound(coding.low),
            high=bound(coding.high),
            shape=(n, act_dim),
            dtype=torch.float32,
            device=dev,
        )
    env.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32, device=dev)
    flag = lambda: Categorical(2, shape=(n, 1), dtype=torch.bool, device=dev)  # noqa: E731
    env.done_spec = Composite(
        done=flag(), terminated=flag(), truncated=flag(), shape=(n,), device=dev
    )
