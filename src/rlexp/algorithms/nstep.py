"""n-step transitions for the replay buffer, computed per env at insert time without crossing the
end of an episode.

A transition at step ``t`` of an env becomes ``(s_t, a_t, R, s_{t+m})`` with
``R = sum_{k<m} gamma^k r_{t+k}`` and ``m = n``, or fewer when the episode ends at ``t+m-1``
(terminated or truncated). The flags and the next observation are those of step ``t+m-1``: a
termination stops the bootstrap (the loss multiplies by ``1 - terminated``), a truncation ends the
sum but the loss still bootstraps from the truncation's next observation. ``steps_to_next_obs``
holds ``m``, so the target discounts by ``gamma ** m`` (TorchRL's value estimators read that key).

A window that is not complete yet (the last ``n - 1`` steps of each env, unless their episode
already ended) waits for the next batch: ``NStepState`` carries those steps over, and the replay
buffer's checkpoint holds it, so a resumed run emits exactly the transitions the uninterrupted one
does.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase

#: The key TorchRL's value estimators read for the number of steps to the next observation.
STEPS_KEY = "steps_to_next_obs"
#: The ``next`` entries taken from the last step of the window (the reward is the window's sum).
_LAST_STEP_KEYS = ("observation", "terminated", "truncated", "done")


@dataclass
class NStepState:
    """The last ``n - 1`` raw steps of each env ``[num_envs, n - 1]`` and which of them are real
    (``valid``: False before an env has taken that many steps)."""

    steps: TensorDictBase
    valid: torch.Tensor


def _flag(td: TensorDictBase, key: str) -> torch.Tensor:
    """A ``next`` flag as a bool tensor ``[E, L]`` (TorchRL stores them ``[E, L, 1]``)."""
    value = td.get(("next", key))
    return value.reshape(value.shape[:2]).bool()


def nstep_transitions(
    batch: TensorDictBase, state: NStepState | None, n: int, gamma: float
) -> tuple[TensorDictBase, NStepState]:
    """The n-step transitions ``batch`` ``[num_envs, T]`` (each env's steps in time order)
    completes, flat ``[M]`` (env-major, then time), and the steps that wait for the next batch."""
    if batch.batch_dims != 2:
        raise ValueError(
            f"algorithm.n_step={n} needs the rollout as [num_envs, T]; got batch size "
            f"{tuple(batch.batch_size)}"
        )
    num_envs = batch.batch_size[0]
    device = batch.device
    if state is None:
        state = NStepState(
            steps=batch[:, :0].clone(),
            valid=torch.zeros(num_envs, 0, dtype=torch.bool, device=device),
        )
    if state.steps.batch_size[0] != num_envs:
        raise ValueError(
            f"the rollout has {num_envs} envs, the n-step window was built for "
            f"{state.steps.batch_size[0]} (env.num_envs changed?)"
        )
    x = torch.cat([state.steps, batch], dim=1)  # [E, L]
    valid = torch.cat(
        [state.valid, torch.ones(batch.batch_size, dtype=torch.bool, device=device)], 1
    )
    held = state.steps.batch_size[1]
    length = x.batch_size[1]
    done = _flag(x, "terminated") | _flag(x, "truncated")
    reward = x.get(("next", "reward"))
    flat_reward = reward.reshape(num_envs, length)

    positions = torch.arange(length, device=device)
    total = torch.zeros_like(flat_reward)
    end = positions.expand(num_envs, length).clone()  # index of the window's last step
    ended = torch.zeros_like(done)  # an episode ended inside the window
    known = torch.zeros_like(done)  # the whole window lies inside x
    for k in range(n):
        at = positions + k
        inside = (at < length).expand(num_envs, length)
        at = at.clamp(max=length - 1)
        take = inside & ~ended
        total = total + torch.where(take, flat_reward[:, at] * (gamma**k), 0.0)
        end = torch.where(take, at.expand(num_envs, length), end)
        ended = ended | (take & done[:, at])
        known = known | (inside & (k == n - 1))
    complete = ended | known
    emitted_before = (positions < held) & ended & (end < held)  # its episode ended in the history
    emit = valid & complete & ~emitted_before

    env_idx, pos_idx = emit.nonzero(as_tuple=True)  # env-major, then time
    end_idx = end[env_idx, pos_idx]
    out = x[env_idx, pos_idx]  # observation, action and any other step entries
    last = x.get("next")[env_idx, end_idx]
    for key in _LAST_STEP_KEYS:
        if key in last.keys():
            out.set(("next", key), last.get(key))
    out.set(("next", "reward"), total[env_idx, pos_idx].reshape(out.get(("next", "reward")).shape))
    out.set(STEPS_KEY, (end_idx - pos_idx + 1).reshape(-1, 1))
    keep = min(n - 1, length)
    new_state = NStepState(steps=x[:, length - keep :].clone(), valid=valid[:, length - keep :])
    return out, new_state


def nstep_state_dict(state: NStepState | None) -> dict | None:
    """The waiting steps as plain values for a checkpoint."""
    if state is None:
        return None
    return {"steps": state.steps.to_dict(), "valid": state.valid.clone()}


def nstep_from_state_dict(value: dict | None) -> NStepState | None:
    """``nstep_state_dict``'s inverse (the caller has checked the tensors' layout)."""
    if value is None:
        return None
    valid = value["valid"]
    steps = TensorDict.from_dict(value["steps"], batch_size=valid.shape, auto_batch_size=False)
    return NStepState(steps=steps, valid=valid)
