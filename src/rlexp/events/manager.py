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
``checkpoint``, ``new_best``). Events of one mode fire in config order.

An event function declares what it accepts, and ``check_event`` (run by the config validation and
by every ``EventManager``) holds its config to it before anything runs: ``PARAMS`` (a
``rlexp.config.native_task.ParamRule`` per parameter: type, length, range; unknown names fail with
the closest one), ``REQUIRED``, ``MODES`` and ``MANAGERS`` (``train`` / ``eval``) it works in, and
``check_params(params, where)`` for rules across parameters. ``check_env(env, where, num_envs,
**params)`` checks it against a built env (e.g. record_video renders one frame):
``EventManager.check_env``. A function without ``PARAMS`` is checked against its signature.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rlexp.common.registry import choices_hint, resolve
from rlexp.config.native_task import EventTermConfig, ParamRule, Unchecked, check_params, plain

MODES = ("startup", "reset", "interval", "step", "trigger")
#: The modes each manager fires (the evaluation manager has no startup) and the trigger signals it
#: sends (rlexp.training.trainer): an event that can never fire is a config error.
MANAGER_MODES = {"train": MODES, "eval": ("reset", "interval", "step", "trigger")}
TRIGGER_SIGNALS = {"train": ("eval_end", "checkpoint", "new_best"), "eval": ("eval_end",)}

EVENT_FUNCS: dict[str, Callable[..., Any]] = {}
_ALLOWED_MODULES: list[str] = ["rlexp.events."]


def register_event(
    name: str,
    *,
    params: dict[str, ParamRule] | None = None,
    required: tuple[str, ...] = (),
    modes: tuple[str, ...] | None = None,
    managers: tuple[str, ...] | None = None,
) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorator: make a function or class available to configs as ``func: <name>``.

    ``params``: a rule per parameter (without them the signature is the check); ``required``: the
    parameters a config must give; ``modes`` / ``managers``: where the event does something (an
    observation-noise event outside ``step`` mode would silently do nothing)."""

    def deco(func: Callable[..., Any]) -> Callable[..., Any]:
        if params is not None:
            func.PARAMS = dict(params)  # type: ignore[attr-defined]
            func.REQUIRED = tuple(required)  # type: ignore[attr-defined]
        if modes is not None:
            func.MODES = tuple(modes)  # type: ignore[attr-defined]
        if managers is not None:
            func.MANAGERS = tuple(managers)  # type: ignore[attr-defined]
        EVENT_FUNCS[name] = func
        return func

    return deco


def allow_event_module(prefix: str) -> None:
    """Let configs name event functions by dotted path under ``prefix`` (from Python code only)."""
    prefix = prefix if prefix.endswith(".") else prefix + "."
    if prefix not in _ALLOWED_MODULES:
        _ALLOWED_MODULES.append(prefix)


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
    event: str | None = None  # the dotted config key of the event being called (for its errors)


def resolve_event_func(name: str, where: str) -> Callable[..., Any]:
    """A registered name, or a dotted path inside the allowlist (the built-in events are registered
    when the package ``rlexp.events`` is imported, which any import of this module does first)."""
    return resolve(
        name,
        where,
        EVENT_FUNCS,
        _ALLOWED_MODULES,
        "event function",
        "register the function with rlexp.events.register_event or allow its module with "
        "allow_event_module",
    )


def check_event(ev: EventTermConfig, where: str) -> Callable[..., Any]:
    """The event's function, after checking its name, mode and parameters (``where``: its dotted
    config key, ``events.train.<name>`` or ``events.eval.<name>``)."""
    func = resolve_event_func(ev.func, where)
    if ev.mode not in MODES:
        raise ValueError(
            f"{where}.mode={ev.mode!r} is not a mode" + choices_hint(ev.mode, list(MODES))
        )
    step = ev.interval_step
    if isinstance(step, bool) or not isinstance(step, int):
        raise TypeError(f"{where}.interval_step={step!r} must be an integer >= 1")
    if ev.mode == "interval" and step < 1:
        raise ValueError(f"{where}.interval_step={step} must be >= 1")
    check_event_params(func, ev, where)
    return func


def _manager_of(where: str) -> str | None:
    """``train`` / ``eval`` for an event key ``events.<manager>.<name>``, else None."""
    parts = where.split(".")
    return (
        parts[1] if len(parts) >= 3 and parts[0] == "events" and parts[1] in MANAGER_MODES else None
    )


def check_event_params(func: Callable[..., Any], ev: EventTermConfig, where: str) -> dict[str, Any]:
    """Check the event's mode against its manager and its function, and its params against the
    function's rules; returns the params (plain dicts and lists) without ``signal``."""
    name = ev.func
    manager = _manager_of(where)
    if manager is not None and ev.mode not in MANAGER_MODES[manager]:
        raise ValueError(
            f"{where}.mode={ev.mode!r}: events.{manager} never fires {ev.mode} events; "
            f"choose from {list(MANAGER_MODES[manager])}"
        )
    managers = getattr(func, "MANAGERS", None)
    if manager is not None and managers and manager not in managers:
        raise ValueError(
            f"{where}: {name} works in events.{' / events.'.join(managers)} only; move it there"
        )
    modes = getattr(func, "MODES", None)
    if modes and ev.mode not in modes:
        raise ValueError(
            f"{where}.mode={ev.mode!r}: {name} does something in mode {' / '.join(modes)} only"
        )
    params = plain(ev.params) if ev.params is not None else {}
    if not isinstance(params, dict):
        raise TypeError(f"{where}.params={params!r} must be a mapping of parameter names to values")
    params = dict(params)
    signal = params.pop("signal", None)
    signals = TRIGGER_SIGNALS.get(manager or "train", ())
    if manager is None:
        signals = tuple(dict.fromkeys(s for v in TRIGGER_SIGNALS.values() for s in v))
    if ev.mode == "trigger":
        if signal is None:
            raise ValueError(
                f"{where}.params.signal is needed with mode=trigger; choose from {list(signals)}"
            )
        if signal not in signals:
            raise ValueError(
                f"{where}.params.signal={signal!r} is never sent"
                + choices_hint(str(signal), list(signals))
            )
    elif signal is not None:
        raise ValueError(
            f"{where}.params.signal={signal!r} applies to mode=trigger only (this event's mode is "
            f"{ev.mode!r}); remove it"
        )
    rules = getattr(func, "PARAMS", None)
    if rules is not None:
        check_params(name, params, rules, f"{where}.params", getattr(func, "REQUIRED", ()))
    else:
        _check_signature(func, name, params, where)
    hook = getattr(func, "check_params", None)
    if hook is not None:
        hook(params, where)
    return params


def _check_signature(
    func: Callable[..., Any], name: str, params: dict[str, Any], where: str
) -> None:
    """An event without rules: its params must at least be keywords its call (and, for a class,
    its ``finalize``) accepts, and give every keyword without a default."""
    targets = [func.__call__, getattr(func, "finalize", None)] if isinstance(func, type) else [func]
    accepted: dict[str, bool] = {}  # name -> required
    for target in targets:
        if target is None:
            continue
        try:
            sig = inspect.signature(target)
        except (TypeError, ValueError):  # a builtin without a signature: nothing to check against
            return
        ps = list(sig.parameters.values())[2 if isinstance(func, type) else 1 :]
        if any(p.kind is p.VAR_KEYWORD for p in ps):
            return
        for p in ps:
            if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
                accepted[p.name] = accepted.get(p.name, False) or p.default is p.empty
    rules = {k: Unchecked() for k in accepted}
    check_params(name, params, rules, f"{where}.params", [k for k, req in accepted.items() if req])


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

    def check_env(self, env: Any, num_envs: int | None = None) -> None:
        """Check every event against a built env of the kind it will run on (e.g. record_video renders
        one frame at its resolution): ValueError / KeyError / TypeError, one line naming the event's
        key and the cause. ``env``: a throwaway build of that env (events may reset it);
        ``num_envs``: how many copies the real env will have (``env`` may have one)."""
        for name, ev, func in self.events:
            hook = getattr(func, "check_env", None)
            if hook is not None:
                params = {k: v for k, v in plain(ev.params).items() if k != "signal"}
                hook(env, f"{self.where}.{name}", num_envs, **params)

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
            ctx.event = f"{self.where}.{name}"
            func(ctx, **params)

    def finalize(self, ctx: EventContext) -> None:
        """Let stateful events write what they gathered (e.g. the eval video) at the end of a round."""
        ctx.rng = self.rng
        for name, ev, func in self.events:
            if hasattr(func, "finalize"):
                ctx.event = f"{self.where}.{name}"
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
