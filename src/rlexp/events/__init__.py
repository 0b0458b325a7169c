"""Events: functions fired by the trainer at startup, on reset, every N iterations, every step or on a signal."""

from rlexp.events.manager import EVENT_FUNCS, MODES, EventContext, EventManager, register_event

__all__ = ["EVENT_FUNCS", "MODES", "EventContext", "EventManager", "register_event"]
