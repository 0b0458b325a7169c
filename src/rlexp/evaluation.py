"""Deterministic evaluation episodes: what the Trainer's ``eval_once`` and ``rlexp eval`` both run."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase


@torch.no_grad()
def run_episodes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    episodes: int,
    on_step: Callable[[TensorDictBase], None] | None = None,
    on_reset: Callable[[TensorDictBase], TensorDictBase] | None = None,
) -> dict[str, float]:
    """Run ``episodes`` episodes spread evenly over the env's copies (each copy's first ones, so
    short episodes are not favoured); returns mean/std return, mean length and success rate.

    ``on_reset`` sees (and may replace) the first tensordict after the env's reset; ``on_step``
    sees each step's tensordict after the policy acted, before the env steps.
    """
    n = int(env.batch_size.numel())
    quota = np.full(n, episodes // n)
    quota[: episodes % n] += 1
    returns: list[float] = []
    lengths: list[int] = []
    successes: list[float] = []
    ep_ret = np.zeros(n)
    ep_len = np.zeros(n, dtype=np.int64)
    ep_success = np.zeros(n)
    done_count = np.zeros(n, dtype=np.int64)
    td = env.reset()
    if on_reset is not None:
        td = on_reset(td)
    while (done_count < quota).any():
        td = policy(td)
        if on_step is not None:
            on_step(td)
        out, td = env.step_and_maybe_reset(td)
        nxt = out["next"]
        ep_ret += nxt["reward"].reshape(n).cpu().numpy()
        ep_len += 1
        if "metrics" in nxt.keys() and "success" in nxt["metrics"].keys():
            ep_success = np.maximum(ep_success, nxt["metrics", "success"].reshape(n).cpu().numpy())
        for i in np.flatnonzero(nxt["done"].reshape(n).cpu().numpy()):
            if done_count[i] < quota[i]:
                returns.append(float(ep_ret[i]))
                lengths.append(int(ep_len[i]))
                successes.append(float(ep_success[i]))
                done_count[i] += 1
            ep_ret[i], ep_len[i], ep_success[i] = 0.0, 0, 0.0
    return {
        "eval/episode_return": float(np.mean(returns)),
        "eval/episode_return_std": float(np.std(returns)),
        "eval/episode_length": float(np.mean(lengths)),
        "eval/success_rate": float(np.mean(successes)),
        "eval/episodes": float(len(returns)),
    }
