"""What a recurrent policy (``policy.memory.type`` lstm / gru) cannot run with: each case one line
(``validate`` raises it as a ConfigError: exit 2, before the run dir exists). docs/policies.md,
"Memory (recurrent policies)", says why for each."""

from __future__ import annotations

from typing import Any

from rlexp.config.rules import MEMORY_BACKENDS


def memory_problem(config: Any) -> str | None:
    """The one-line refusal of a recurrent policy in ``config``'s setting, or None where it runs."""
    memory = getattr(config.policy, "memory", None)
    if memory is None or memory.type == "none":
        return None
    a, e = config.algorithm, config.env
    what = f"policy.memory.type={memory.type}"
    if a.name != "ppo":
        return (
            f"{what}: algorithm={a.name} trains feed-forward policies only (the recurrent "
            "sequence loss is PPO's); use algorithm=ppo, or policy.memory.type=none"
        )
    if e.backend not in MEMORY_BACKENDS:
        return (
            f"{what}: env.backend={e.backend!r} is stepped by TorchRL's generic loop, which does "
            f"not carry the hidden state; use one of {list(MEMORY_BACKENDS)} (e.g. "
            "env.backend=gymnasium), or policy.memory.type=none"
        )
    if getattr(config.trainer, "precision", "fp32") != "fp32":
        return (
            f"{what}: trainer.precision={config.trainer.precision}, but the recurrent core runs "
            "in float32 only; use trainer.precision=fp32, or policy.memory.type=none"
        )
    if str(a.compile).strip().lower() == "true":
        return (
            f"{what}: algorithm.compile=true, but the recurrent sequence loss runs eager (its "
            "reset points differ per minibatch); use algorithm.compile=auto or false"
        )
    stepping = [
        name
        for name, term in config.events.train.items()
        if (term.get("mode") if isinstance(term, dict) else getattr(term, "mode", None))
        in ("step", "reset")
    ]
    if stepping:
        return (
            f"{what}: events.train.{stepping[0]} fires at every step or reset, which runs the "
            "rollout through TorchRL's generic loop (no hidden state there); remove it, or use "
            "policy.memory.type=none"
        )
    return None
