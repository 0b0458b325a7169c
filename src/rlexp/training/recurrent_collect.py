"""The collector's lean loop for a recurrent policy (policies/memory.py): the hidden state carried
from step to step and from rollout to rollout, zeroed where an episode ended (terminated or
truncated), and stored in the rollout as the policy read it.

Rollout entries besides the MLP policy's: ``("recurrent_state", name)`` [E, T, layers, H], the state
*before* each step (zeros at an episode's first step), and ``"is_init"`` bool [E, T, 1], True at an
episode's first step (TorchRL's convention). PPO cuts the rollout into sequences and starts each from
its stored state (algorithms/recurrent_ppo.py).

What is carried between rollouts (the state to act from next, and which envs start an episode) is
``Carry``: the collector holds it, the trainer's checkpoint saves it, a resume puts it back, so a
run stopped mid-episode continues bit-identically. Envs and policy on one device, or on two with
one copy each way per step (as the MLP loop). The numpy sampler does not apply: torch only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase


@dataclass
class Carry:
    """What a recurrent collector carries from one step (and rollout) to the next."""

    state: dict[str, torch.Tensor]  # the state to act from next, [E, layers, H] per name
    is_init: torch.Tensor  # bool [E, 1]: the next step is an episode's first

    def to_plain(self) -> dict[str, Any]:
        """The checkpoint's form (tensors in dicts: ``torch.load(weights_only=True)``)."""
        return {
            "state": {k: v.detach().cpu().clone() for k, v in self.state.items()},
            "is_init": self.is_init.detach().cpu().clone(),
        }

    @classmethod
    def from_plain(cls, value: dict[str, Any], device: torch.device) -> Carry:
        return cls(
            {k: v.to(device) for k, v in value["state"].items()}, value["is_init"].to(device)
        )


def fresh_carry(policy: Any, num_envs: int, device: torch.device) -> Carry:
    """Every env at an episode's start: zero state, ``is_init`` True."""
    state = policy.initial_state(num_envs, device)
    return Carry(state, torch.ones(num_envs, 1, dtype=torch.bool, device=device))


def recurrent_rollout(
    env: Any,
    policy: Any,
    steps: int,
    obs: torch.Tensor | TensorDictBase,
    carry: Carry | None,
    to_policy: torch.device,
    to_env: torch.device | None,
) -> tuple[TensorDictBase, torch.Tensor | TensorDictBase, Carry]:
    """``steps`` steps of every env from ``obs`` and ``carry`` (None: every env starts an episode)
    -> (the rollout [E, T] on the policy's device, the observation to act on next, the carry)."""
    sample = policy.sampler()
    step = getattr(env, "step_tensors", None) or env.step_action
    num_envs = int(env.batch_size.numel())
    if carry is None:
        carry = fresh_carry(policy, num_envs, to_policy)
    state, is_init = carry.state, carry.is_init
    names = list(state)
    keys = ("observation", *policy.out_keys)
    root: dict[str, list[Any]] = {k: [] for k in keys}
    states: dict[str, list[torch.Tensor]] = {n: [] for n in names}
    inits: list[torch.Tensor] = []
    nexts: list[Any] = []
    for _ in range(steps):
        if to_env is not None:
            obs = obs.to(to_policy)
        out, new_state = sample(obs, state)
        action = out[-2]
        nxt = step(action if to_env is None else action.to(to_env))
        root["observation"].append(obs)
        for key, value in zip(keys[1:], out, strict=True):
            root[key].append(value)
        for n in names:
            states[n].append(state[n])
        inits.append(is_init)
        nexts.append(nxt)
        done = nxt.get("done") if isinstance(nxt, TensorDictBase) else nxt["done"]
        is_init = done.reshape(num_envs, 1).to(to_policy, torch.bool)
        keep = (~is_init).to(torch.float32).reshape(num_envs, 1, 1)
        state = {n: v * keep for n, v in new_state.items()}  # an ended episode's state: zeros
        obs = env.autoreset_observation(nxt)
    size = [*env.batch_size, steps]
    batch: dict[str, Any] = {k: torch.stack(v, dim=1) for k, v in root.items()}
    batch["recurrent_state"] = TensorDict(
        {n: torch.stack(v, dim=1) for n, v in states.items()}, batch_size=size
    )
    batch["is_init"] = torch.stack(inits, dim=1)
    if isinstance(nexts[0], dict):
        nxt_td: Any = TensorDict._new_unsafe(
            {k: torch.stack([n[k] for n in nexts], dim=1) for k in nexts[0]},
            batch_size=size,
            device=env.device,
        )
    else:
        nxt_td = torch.stack(nexts, dim=1)
    batch["next"] = nxt_td if to_env is None else nxt_td.to(to_policy)
    rollout = TensorDict(batch, batch_size=size, device=to_policy)
    return rollout, obs, Carry(state, is_init)
