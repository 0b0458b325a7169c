"""Learners, one file each: PPO (``ppo.py``), GRPO (``grpo.py``); what they share is in ``base.py``.

Importing this package is cheap: torch and TorchRL load when ``make_algorithm`` first runs.

Layer 2 (pieces). May import: layers 0-1 (``config``, ``runtime.distributed``) and the other pieces
(``policies``, ``checkpoints``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rlexp.algorithms.base import Algorithm, GradSync
    from rlexp.config.schema import BaseAlgorithmConfig
    from rlexp.policies.actor_critic import Policy

#: ``algorithm.name`` values make_algorithm builds.
ALGORITHMS = ("ppo", "grpo")


def make_algorithm(
    cfg: BaseAlgorithmConfig,
    policy: Policy,
    total_iterations: int,
    nan_guard: bool = True,
    grad_sync: GradSync | None = None,
) -> Algorithm:
    """Build the configured learner around ``policy`` (``grad_sync``: the distributed all-reduce)."""
    if cfg.name == "ppo" and getattr(policy, "recurrent", False):
        from rlexp.algorithms.recurrent_ppo import RecurrentPPO

        return RecurrentPPO(cfg, policy, total_iterations, nan_guard, grad_sync)
    if cfg.name == "ppo":
        from rlexp.algorithms.ppo import PPO

        return PPO(cfg, policy, total_iterations, nan_guard, grad_sync)
    if cfg.name == "grpo":
        from rlexp.algorithms.grpo import GRPO

        return GRPO(cfg, policy, total_iterations, nan_guard, grad_sync)
    raise ValueError(f"algorithm.name={cfg.name!r}; choose from {list(ALGORITHMS)}")
