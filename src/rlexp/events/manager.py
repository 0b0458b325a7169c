"""The event manager: a small closed set of modes, functions looked up in a registry.

A config names an event function by its registered name, or by a dotted path inside an allowlist
of modules (``rlexp.events.``, plus whatever Python code adds with ``allow_event_module``), so a
config file cannot import arbitrary code. A registered *function* is called as
``func(ctx, **params)``; a registered *class* is instantiated once per manager and its instance
called the same way, and may keep state (``state_dict`` / ``load_state_dict``) and write files at
the end of an evaluation round (``finalize(ctx)``).

Modes: ``startup`` once before training (not again on resume); ``reset`` when envs reset, with
their ids; ``interval`` every ``interval_step`` calls (training: iterations; evaluation: eval
steps); ``step`` every env step; ``trigger`` on a named signal (``params.signal``: ``eval_end``,
``checkpoint``, ``new_best``, ...). Events of one mode fire in config order.
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rlexp.config.native_task import EventTermConfig

MODES = ("startup", "reset", "interval", "step", "trigger")

EVENT_FUNCS: dict[str, Callable[..., Any]] = {}
_ALLOWED_MODULES: list[str] = ["rlexp.events."]


def register_event(name: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorator: make a function or class available to configs as ``func: <name>``."""

    def deco(func: Callable[..., Any]) -> Callable[..., Any]:
        EVENT_FUNCS[name] = func
        return func

    return deco


def allow_event_module(prefix: str) -> None:
    """Let configs name event functions by dotted path under ``prefix`` (from Python code only)."""
    if prefix not in _ALLOWED_MODULES:
        _ALLOWED_MODULES.append(prefix if prefix.endswith(".") else prefix + ".")


@dataclass
class EventContext:
    """What an event function sees: no back-reference to the trainer."""

    env: Any = None
    env_ids: np.ndarray | None = None  # ids of the envs concerned (reset events); None: all
    global_step: int = 0
    rng: np.random.Generator | None = None  # the manager's generator (checkpointed)
    run_dir: Path | None = None
    tensordict: Any = (
        None  # step events: the step's tensordict (phase "action": before the env step)
    )
    phase: str | None = None  # step events: "action" (before env.step) or "observation" (after)
    batch: Any = None  # interval events during training: the rollout just collected
    metrics: dict[str, float] = field(default_factory=dict)  # trigger events: e.g. the eval metrics
    signal: str | None = None


def _choices_hint(value: str, choices: list[str]) -> str:
    close = difflib.get_close_matches(value, choices, n=1)
    return f"; choose from {sorted(choices)}" + (f"; did you mean {close[0]!r}?" if close else "")


def resolve_event_func(name: str, where: str) -> Callable[..., Any]:
    """A registered name, or a dotted path inside the allowlist."""
    from rlexp.events import builtin  # noqa: F401  (registers the built-in events)

    if name in EVENT_FUNCS:
        return EVENT_FUNCS[name]
    if "." in name:
        if not any(name.startswith(p) for p in _ALLOWED_MODULES):
            raise ValueError(
                f"{where}.func={name!r}: dotted paths must be inside {_ALLOWED_MODULES} "
                "(a config may not import arbitrary code); register the function with "
                "rlexp.events.register_event or allow its module with allow_event_module"
            )
        module, _, attr = name.rpartition(".")
        try:
            return getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as exc:
            raise ValueError(f"{where}.func={name!r} cannot be imported: {exc}") from exc
    raise ValueError(
        f"{where}.func={name!r} is not a known event function"
        + _choices_hint(name, list(EVENT_FUNCS))
    )


def check_event(ev: EventTermConfig, where: str) -> Callable[..., Any]:
    """The event's function, after checking its name and mode (``where``: its dotted config key)."""
    func = resolve_event_func(ev.func, where)
    if ev.mode not in MODES:
        raise ValueError(
            f"{where}.mode={ev.mode!r} is not a mode" + _choices_hint(ev.mode, list(MODES))
        )
    if ev.mode == "interval" and ev.interval_step < 1:
        raise ValueError(f"{where}.interval_step={ev.interval_step} must be >= 1")
    return func


class EventManager:
    """Fires the configured events, in config order, with per-event counters and one RNG."""

    def __init__(self, events: dict[str, EventTermConfig], where: str, seed: int = 0) -> None:
        self.where = where
        self.events: list[tuple[str, EventTermConfig, Callable[..., Any]]] = []
        for name, ev in events.items():
            func = check_event(ev, f"{where}.{name}")
            if isinstance(func, type):
                func = func()
            self.events.append((name, ev, func))
        self.counters = {name: 0 for name, _, _ in self.events}
        self.rng = np.random.default_rng(seed)

    def has(self, *modes: str) -> bool:
        return any(ev.mode in modes for _, ev, _ in self.events)

    def fire(self, mode: str, ctx: EventContext, signal: str | None = None) -> None:
        """Call every event of ``mode`` (for ``trigger``: those whose ``params.signal`` matches)."""
        ctx.rng = self.rng
        ctx.signal = signal
        for name, ev, func in self.events:
            if ev.mode != mode:
                continue
            params = dict(ev.params)
            if mode == "trigger" and params.pop("signal", None) != signal:
                continue
            params.pop("signal", None)
            self.counters[name] += 1
            if mode == "interval" and self.counters[name] % ev.interval_step != 0:
                continue
            func(ctx, **params)

    def finalize(self, ctx: EventContext) -> None:
        """Let stateful events write what they gathered (e.g. the eval video) at the end of a round."""
        ctx.rng = self.rng
        for _, ev, func in self.events:
            if hasattr(func, "finalize"):
                func.finalize(ctx, **{k: v for k, v in ev.params.items() if k != "signal"})

    def state_dict(self) -> dict[str, Any]:
        return {
            "counters": dict(self.counters),
            "rng": self.rng.bit_generator.state,
            "events": {
                name: func.state_dict()
                for name, _, func in self.events
                if hasattr(func, "state_dict")
            },
        }

    def load_state_dict(self, sd: dict[str, Any], env: Any = None) -> None:
        self.counters.update(sd.get("counters", {}))
        if "rng" in sd:
            self.rng.bit_generator.state = sd["rng"]
        for name, _, func in self.events:
            if name in sd.get("events", {}) and hasattr(func, "load_state_dict"):
                func.load_state_dict(sd["events"][name], env)
