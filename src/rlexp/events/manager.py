"""The event manager: a small closed set of modes, functions looked up in a registry.

A config names an event function by its registered name (never an import path), so a config file
cannot import arbitrary code. Each function is called as ``func(ctx, **params)`` with an
``EventContext`` holding what an event may touch: the env, the env ids concerned, the step.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rlexp.config.native_task import EventTermConfig

#: startup: once before training; reset: when envs reset (with their ids); interval: every
#: ``interval_step`` iterations; step: every env step; trigger: on a named signal.
MODES = ("startup", "reset", "interval", "step", "trigger")

EVENT_FUNCS: dict[str, Callable[..., Any]] = {}


def register_event(name: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorator: make ``func`` available to configs as ``func: <name>``."""

    def deco(func: Callable[..., Any]) -> Callable[..., Any]:
        EVENT_FUNCS[name] = func
        return func

    return deco


@dataclass
class EventContext:
    """What an event function sees."""

    env: Any = None
    env_ids: Any = None  # ids of the envs concerned (reset events), None for all
    global_step: int = 0
    signal: str | None = None  # the trigger's name
    extras: dict[str, Any] = field(default_factory=dict)


def _choices_hint(value: str, choices: list[str]) -> str:
    close = difflib.get_close_matches(value, choices, n=1)
    return f"; choose from {sorted(choices)}" + (f"; did you mean {close[0]!r}?" if close else "")


class EventManager:
    """Fires the configured events, in config order, with per-event counters."""

    def __init__(self, events: dict[str, EventTermConfig], where: str) -> None:
        self.events: list[tuple[str, EventTermConfig, Callable[..., Any]]] = []
        for name, ev in events.items():
            if ev.func not in EVENT_FUNCS:
                raise ValueError(
                    f"{where}.{name}.func={ev.func!r} is not a known event function"
                    + _choices_hint(ev.func, list(EVENT_FUNCS))
                )
            if ev.mode not in MODES:
                raise ValueError(f"{where}.{name}.mode={ev.mode!r} is not a mode" + _choices_hint(ev.mode, list(MODES)))
            if ev.mode == "interval" and ev.interval_step < 1:
                raise ValueError(f"{where}.{name}.interval_step={ev.interval_step} must be >= 1")
            self.events.append((name, ev, EVENT_FUNCS[ev.func]))
        self.counters = {name: 0 for name, _, _ in self.events}

    def fire(self, mode: str, ctx: EventContext, signal: str | None = None) -> None:
        """Call every event of ``mode`` (for ``trigger``: those whose ``params.signal`` matches)."""
        for name, ev, func in self.events:
            if ev.mode != mode:
                continue
            params = dict(ev.params)
            if mode == "trigger" and params.pop("signal", None) != signal:
                continue
            self.counters[name] += 1
            if mode == "interval" and self.counters[name] % ev.interval_step != 0:
                continue
            func(ctx, **params)

    def state_dict(self) -> dict[str, Any]:
        return {"counters": dict(self.counters)}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.counters.update(sd.get("counters", {}))
