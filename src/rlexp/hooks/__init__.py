"""Trainer hooks: user code at fixed points of the training loop (see ``rlexp.hooks.base``)."""

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
