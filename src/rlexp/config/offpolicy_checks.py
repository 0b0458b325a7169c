"""The cross-field rules of ``algorithm=sac`` / ``algorithm=td3`` (``validate`` raises what these
return as one line), and the one value they derive: ``trainer.frames_per_batch`` is
``env.num_envs * algorithm.train_freq`` (a rollout is ``train_freq`` steps of every env)."""

from __future__ import annotations

from typing import Any

from rlexp.config.schema_base import BaseAlgorithmConfig
from rlexp.config.schema_offpolicy import OFF_POLICY, ON_POLICY_ONLY

#: algorithm.name -> the policy.name its networks need.
POLICY_OF = {"sac": "sac", "td3": "td3"}


def is_off_policy(algorithm: Any) -> bool:
    return getattr(algorithm, "name", None) in OFF_POLICY


def distributed_refusal(algorithm: Any) -> str:
    """``--distributed`` with SAC / TD3, as one line: one learner, one process's replay buffer."""
    return (
        f"--distributed: algorithm={algorithm.name} learns from one process's replay buffer; run "
        "it without --distributed (a sweep runs seeds in parallel: python train.py -m seed=0,1,2)"
    )


def derive_frames_per_batch(config: Any) -> None:
    """SAC / TD3: ``trainer.frames_per_batch = env.num_envs * algorithm.train_freq``."""
    a = config.algorithm
    if is_off_policy(a) and isinstance(a.train_freq, int) and a.train_freq >= 1:
        config.trainer.frames_per_batch = config.env.num_envs * a.train_freq


def off_policy_problem(config: Any) -> str | None:
    """The first thing about ``config`` that SAC / TD3 (or PPO / GRPO with their networks) cannot
    run with, as one line naming the key, the value and the fix; None when there is nothing."""
    a, p = config.algorithm, config.policy
    if not is_off_policy(a):
        if p.name in POLICY_OF.values():
            return (
                f"policy.name={p.name!r} is for algorithm={p.name} (a Q-function critic); "
                f"algorithm={a.name} needs policy=mlp (actor_critic) or policy=actor_only"
            )
        return None
    wanted = POLICY_OF[a.name]
    if p.name != wanted:
        return (
            f"algorithm={a.name} needs policy.name={wanted!r} (its actor and twin Q networks), not "
            f"{p.name!r}: use policy={wanted} (algorithm={a.name} selects it unless policy= is given)"
        )
    defaults = BaseAlgorithmConfig()
    for key in ON_POLICY_ONLY:
        value = getattr(a, key)
        if value != getattr(defaults, key):
            return (
                f"algorithm.{key}={value!r} is a PPO / GRPO option; algorithm={a.name} has none "
                f"(docs/{a.name}.md): remove it (batch_size is the transitions per gradient step)"
            )
    if a.batch_size > a.buffer_size:
        return (
            f"algorithm.batch_size={a.batch_size} must be at most algorithm.buffer_size="
            f"{a.buffer_size} (the transitions each gradient step samples from the buffer)"
        )
    return None
