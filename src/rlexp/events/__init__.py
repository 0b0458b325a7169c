"""Events: functions fired by the trainer at startup, on reset, every N iterations, every step or on a signal."""

from rlexp.events.manager import (
    EVENT_FUNCS,
    MODES,
    EventContext,
    EventManager,
    allow_event_module,
    register_event,
)

__all__ = [
    "EVENT_FUNCS",
    "MODES",
    "EventContext",
    "EventManager",
    "allow_event_module",
    "register_event",
]
