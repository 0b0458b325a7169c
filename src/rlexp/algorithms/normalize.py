"""Reward scaling for PPO (``algorithm.normalize_rewards``): the reward part of SB3's
``VecNormalize`` / CleanRL's ``NormalizeReward``, applied to a whole rollout inside the update.

Per env a running discounted return ``R_t = gamma * R_{t-1} + r_t`` (back to 0 after a step that
ended the episode); a running variance of ``R`` over all envs and steps, updated step by step with
the ``num_envs`` values of ``R_t``; the reward the update learns from is ``r_t / sqrt(var_t + eps)``.
The statistics start as Gymnasium's / SB3's ``RunningMeanStd`` does (mean 0, variance 1, count
1e-4). The collection policy never sees rewards, so scaling a rollout after it was collected gives
the rewards the wrapper would have given step by step.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import torch

log = logging.getLogger(__name__)

#: Sums a tensor over ranks (``rlexp.runtime.distributed.all_reduce_sum``): all ranks then agree.
ReduceSum = Callable[[torch.Tensor], torch.Tensor]

#: RunningMeanStd's starting count (Gymnasium, SB3): the prior variance of 1 weighs this much.
INITIAL_COUNT = 1e-4


#: Up to this many envs the running returns are computed env by env on Python floats (~0.1 us a
#: step) rather than step by step on tensors of all envs (~10 us a step whatever their number).
PYTHON_LOOP_MAX_ENVS = 64


def discounted_returns(
    reward: torch.Tensor, ended: torch.Tensor, start: torch.Tensor, gamma: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """``R_t = gamma * R_{t-1} + r_t`` along the last dim of ``reward`` [*E, T] (float64), from
    ``start`` [*E], back to 0 after each step where ``ended``; returns all ``R_t`` and the running
    ``R`` after the last step. The same float64 operations in the same order either way."""
    envs, steps = reward.shape[:-1], reward.shape[-1]
    if start.numel() <= PYTHON_LOOP_MAX_ENVS and reward.device.type == "cpu":
        rows, last = [], []
        for rew, end, acc in zip(
            reward.reshape(-1, steps).tolist(),
            ended.reshape(-1, steps).tolist(),
            start.reshape(-1).tolist(),
            strict=True,
        ):
            row = []
            for x, e in zip(rew, end, strict=True):
                acc = acc * gamma + x
                row.append(acc)
                if e:
                    acc = 0.0
            rows.append(row)
            last.append(acc)
        returns = torch.tensor(rows, dtype=torch.float64).reshape(reward.shape)
        return returns, torch.tensor(last, dtype=torch.float64).reshape(envs)
    returns = torch.empty_like(reward)
    running = start
    for t in range(steps):
        running = running * gamma + reward[..., t]
        returns[..., t] = running
        running = running.masked_fill(ended[..., t], 0.0)
    return returns, running


class RewardNormalizer:
    """Running std of the discounted return; ``scale(reward, done)`` scales one rollout [*E, T, 1]."""

    def __init__(self, gamma: float, eps: float = 1e-8) -> None:
        self.gamma = gamma
        self.eps = eps
        # float64 like the references' numpy statistics: sums over millions of steps stay exact
        self.mean = torch.zeros((), dtype=torch.float64)
        self.var = torch.ones((), dtype=torch.float64)
        self.count = torch.full((), INITIAL_COUNT, dtype=torch.float64)
        self.returns: torch.Tensor | None = None  # per env [*E]; None until the first rollout

    @torch.no_grad()
    def scale(
        self, reward: torch.Tensor, done: torch.Tensor, reduce_sum: ReduceSum | None = None
    ) -> torch.Tensor:
        """Fold the rollout's returns into the statistics and return ``reward / sqrt(var_t + eps)``.

        ``reward`` and ``done`` are [*E, T, 1] (time is the last batch dim). ``reduce_sum`` sums the
        per-step statistics over ranks: one all-reduce per rollout, and every rank ends with the
        same statistics (each keeps its own envs' running returns)."""
        device = reward.device
        r = reward.squeeze(-1).to(torch.float64)  # [*E, T]
        ended = done.squeeze(-1).to(device=device, dtype=torch.bool)
        envs, steps = r.shape[:-1], r.shape[-1]
        if self.returns is None or self.returns.shape != envs:
            if self.returns is not None:
                log.warning(
                    "[ppo] reward normaliser: %s envs in the rollout, %s in its running returns; "
                    "starting them again from 0",
                    tuple(envs),
                    tuple(self.returns.shape),
                )
            self.returns = torch.zeros(envs, dtype=torch.float64, device=device)
        self.mean, self.var, self.count, self.returns = (
            t.to(device) for t in (self.mean, self.var, self.count, self.returns)
        )
        returns, self.returns = discounted_returns(r, ended, self.returns, self.gamma)

        # Per step: count, and sum and sum of squares of R - mean (centred on the statistics'
        # mean before this rollout, the same on every rank: stable, and reducible by summing).
        centred = (returns - self.mean).reshape(-1, steps)
        stats = torch.stack(
            [
                torch.full((steps,), float(centred.shape[0]), dtype=torch.float64, device=device),
                centred.sum(0),
                centred.pow(2).sum(0),
            ]
        )
        if reduce_sum is not None:
            stats = reduce_sum(stats)
        # Statistics after step t = the running ones merged with all R of steps 0..t (Chan et al.'s
        # parallel update): what updating step by step gives, without a loop over the steps.
        n, s1, s2 = stats.cumsum(-1)
        batch_mean = s1 / n  # relative to self.mean
        batch_var = (s2 / n - batch_mean.pow(2)).clamp_min(0.0)
        total = self.count + n
        var = (
            self.var * self.count + batch_var * n + batch_mean.pow(2) * self.count * n / total
        ) / total
        mean = self.mean + batch_mean * n / total
        self.mean, self.var, self.count = mean[-1], var[-1], total[-1]
        scaled = r / torch.sqrt(var + self.eps)  # var [T] broadcasts over the envs
        return scaled.to(reward.dtype).unsqueeze(-1)

    def std(self) -> float:
        """The current ``sqrt(var + eps)`` rewards are divided by."""
        return float(torch.sqrt(self.var + self.eps))

    def state_dict(self) -> dict[str, Any]:
        return {
            "mean": self.mean.clone(),
            "var": self.var.clone(),
            "count": self.count.clone(),
            "returns": None if self.returns is None else self.returns.clone(),
        }

    def load_state_dict(self, sd: dict[str, Any], keep_returns: bool = True) -> None:
        """Restore ``state_dict``; ``keep_returns=False``: the envs start new episodes (returns 0)."""
        check_state(sd)
        self.mean = sd["mean"].to(torch.float64).clone()
        self.var = sd["var"].to(torch.float64).clone()
        self.count = sd["count"].to(torch.float64).clone()
        returns = sd.get("returns")
        if returns is None:
            self.returns = None
        elif keep_returns:
            self.returns = returns.to(torch.float64).clone()
        else:
            self.returns = torch.zeros_like(returns, dtype=torch.float64)


def check_state(sd: dict[str, Any]) -> None:
    """``ValueError`` naming the field when ``sd`` is not what ``state_dict`` writes: float64 scalar
    mean, var >= 0 and count > 0 (all finite), and running returns of one dimension or None. A
    checkpoint's count of -1 or a var of the wrong shape would otherwise scale every later reward
    by garbage, or fail only mid-run."""
    for key in ("mean", "var", "count"):
        value = sd.get(key)
        if not isinstance(value, torch.Tensor) or value.dtype != torch.float64 or value.dim():
            shown = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise ValueError(f"{key} is {shown}; expected a float64 scalar tensor")
        if not bool(torch.isfinite(value)):
            raise ValueError(f"{key}={float(value)}; expected a finite number")
    if float(sd["var"]) < 0 or float(sd["count"]) <= 0:
        raise ValueError(
            f"var={float(sd['var'])}, count={float(sd['count'])}; expected var >= 0 and count > 0"
        )
    returns = sd.get("returns")
    if returns is not None and (
        not isinstance(returns, torch.Tensor)
        or returns.dtype != torch.float64
        or returns.dim() != 1
        or not bool(torch.isfinite(returns).all())
    ):
        raise ValueError("returns is not a finite float64 tensor of one dimension (one per env)")
