"""Observation groups an env declares by its observation's top-level keys (docs/policies.md).

The rsl_rl / Isaac Lab convention, for a Gymnasium ``Dict`` and a TorchRL ``Composite`` alike: a
top-level key named ``critic`` (or ``policy``) is a group of its own, the rest is the ``policy``
group; and an observation with a top-level ``policy`` key (Isaac Lab's wrappers, rsl_rl 3.x's
TensorDict) declares its groups, so every top-level key is one (``teacher``, ``perception``, ...).
"""

from __future__ import annotations

from collections.abc import Iterable

#: Top-level keys that are observation groups of their own, whatever the other keys are.
GROUP_NAMES = ("policy", "critic")


def group_rule(top_keys: Iterable[str]):
    """``top key -> group`` for an observation whose top-level keys are ``top_keys``."""
    declared = "policy" in set(top_keys)

    def group(top: str) -> str:
        return top if declared or top in GROUP_NAMES else "policy"

    return group
