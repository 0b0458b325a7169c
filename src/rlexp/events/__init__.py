"""Events: functions fired by the trainer at startup, on reset, every N iterations, every step or on a signal.

Importing the package registers the built-in events (``rlexp.events.builtin``), so the manager
never has to import them back.

Layer 2 (pieces). May import: layers 0-1 and the other pieces (``envs``).
"""

from rlexp.events import builtin  # noqa: F401  (registers randomize_physics, record_video, ...)
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
