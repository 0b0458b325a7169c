"""Trainer hooks: user code at fixed points of the training loop (see ``rlexp.hooks.base``).
Importing the package registers the built-in hooks (``rlexp.hooks.builtin``).

Layer 2 (pieces). May import: layers 0-1 and the other pieces (``pbt``, ``checkpoints``).
"""

from rlexp.hooks import (
    builtin,  # noqa: F401,E402  (registers stop_at, schedule, ...)
    optuna_prune,  # noqa: F401,E402  (registers optuna_prune: an Optuna sweep's pruning)
    pbt,  # noqa: F401,E402  (registers pbt: Population Based Training)
)
from rlexp.hooks.base import (
    END_STATUSES,
    HOOK_FUNCS,
    POINTS,
    HookControl,
    HookError,
    HookManager,
    HookState,
    allow_hook_module,
    check_hook,
    register_hook,
)

__all__ = [
    "END_STATUSES",
    "HOOK_FUNCS",
    "POINTS",
    "HookControl",
    "HookError",
    "HookManager",
    "HookState",
    "allow_hook_module",
    "check_hook",
    "register_hook",
]
