"""The TorchRL specs every rlexp env presents, whatever its backend: a flat float32 ``observation``
[n, obs_dim], a ``Bounded`` float32 or ``MultiCategorical`` int64 action [n, act_dim], a float32
reward [n, 1] and bool ``done`` / ``terminated`` / ``truncated`` [n, 1]."""

from __future__ import annotations

import torch
from torchrl.data import Bounded, Categorical, Composite, MultiCategorical, Unbounded
from torchrl.envs import EnvBase

from rlexp.envs.spaces import ActionCoding


def set_specs(env: EnvBase, n: int, obs_dim: int, coding: ActionCoding) -> None:
    """Give ``env`` (batch size [n], on its own device) rlexp's specs for ``coding``'s actions."""
    dev, act_dim = env.device, coding.dim
    env.observation_spec = Composite(
        observation=Unbounded(shape=(n, obs_dim), dtype=torch.float32, device=dev),
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
