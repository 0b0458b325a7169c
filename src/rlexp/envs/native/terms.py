"""The env's term tables, built from a task's term configuration: each term looked up in its registry,
its mode chosen and its params checked against its rules and the built state, before anything runs.

Every error names the term's config key (``rewards.reach.params.sigma``); ``named_error`` does the
same for a term that fails when it is called.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from dataclasses import asdict, is_dataclass
from typing import TYPE_CHECKING, Any

from rlexp.config.native_task import Number, Unchecked, check_group, check_params, plain
from rlexp.envs.native.actions import ACTIONS
from rlexp.envs.native.events import EVENTS
from rlexp.envs.native.observations import OBSERVATIONS
from rlexp.envs.native.registry import unknown_name_message
from rlexp.envs.native.rewards import REWARDS

if TYPE_CHECKING:
    from rlexp.envs.native.state import SimState

EVENT_MODES = ("startup", "reset", "interval")
OBSERVATION_MODES = ("add", "modify")
REWARD_MODES = ("add", "replace")

#: The errors a term may raise about its config: re-raised with the term's key in front.
TERM_ERRORS = (KeyError, ValueError, TypeError)


def named_error(exc: Exception, where: str) -> Exception:
    """A term's KeyError / ValueError / TypeError with its config key in front of the message
    (``raise named_error(exc, where) from exc`` in an ``except TERM_ERRORS``: free when nothing fails)."""
    msg = str(exc.args[0] if exc.args else exc)
    kind = next(k for k in TERM_ERRORS if isinstance(exc, k))
    return kind(msg if msg.startswith(where) else f"{where}: {msg}")


def as_dict(cfg: Any) -> dict[str, Any]:
    """A term entry (dataclass or mapping) as a plain dict."""
    if is_dataclass(cfg):
        return asdict(cfg)
    return dict(cfg)


def _check_params(
    func: Any, params: dict[str, Any], where: str, skip: int, env: Any = None
) -> None:
    """Fail at build time, naming the config key, if ``params`` do not fit ``func``: its rules
    (``PARAMS``, set by the registries: types, lengths, ranges, and with ``env`` the names and joint
    indices they refer to), else at least its signature."""
    target = func.__init__ if isinstance(func, type) else func
    sig = inspect.signature(target)
    names = list(sig.parameters)[skip:]
    required = [n for n in names if sig.parameters[n].default is inspect.Parameter.empty]
    rules = getattr(func, "PARAMS", None)
    if rules is None:
        rules = {n: Unchecked() for n in names}
    check_params(func.__name__, params, rules, f"{where}.params", required, env)


def _choose(value: str, choices: tuple[str, ...], where: str) -> str:
    if value not in choices:
        raise ValueError(unknown_name_message("mode", value, choices, where))
    return value


def build_action_terms(
    actions: Mapping[str, Any] | None, env: SimState
) -> tuple[list[tuple[slice, Any]], int]:
    """The action terms, built on ``env``, each with its slice of the action; and the action size."""
    if not actions:
        raise ValueError("env.native.actions is empty; add an action term such as DeltaQposTerm")
    terms = []
    dim = 0
    for key, term in actions.items():
        t = as_dict(term)
        cls = ACTIONS.get(t["func"], f"actions.{key}")
        params = plain(t.get("params") or {})
        _check_params(cls, params, f"actions.{key}", skip=2, env=env)
        try:
            inst = cls(env, **params)
        except TERM_ERRORS as exc:
            raise named_error(exc, f"actions.{key}") from exc
        terms.append((slice(dim, dim + inst.action_dim), inst))
        dim += inst.action_dim
    return terms, dim


def build_event_terms(
    events: Mapping[str, Any] | None, env: SimState
) -> tuple[list[tuple[str, Any, dict[str, Any], int]], ...]:
    """The startup, reset and interval events: ``(key, func, params, interval_step)`` each."""
    startup, reset, interval = [], [], []
    for key, term in (events or {}).items():
        t = as_dict(term)
        func = EVENTS.get(t["func"], f"events.{key}")
        mode = _choose(t.get("mode", "reset"), EVENT_MODES, f"events.{key}.mode")
        params = plain(t.get("params") or {})
        _check_params(func, params, f"events.{key}", skip=2, env=env)
        every = t.get("interval_step", 1)
        Number(ge=1, integer=True).check(every, f"events.{key}.interval_step")
        entry = (key, func, params, int(every))
        {"startup": startup, "reset": reset, "interval": interval}[mode].append(entry)
    return startup, reset, interval


def build_observation_terms(
    observations: Mapping[str, Any] | None, env: SimState
) -> list[tuple[str, Any, str, str, dict[str, Any], str]]:
    """The observation terms, in config order: ``(key, func, mode, name, params, group)`` each."""
    terms = []
    for key, term in (observations or {}).items():
        t = as_dict(term)
        func = OBSERVATIONS.get(t["func"], f"observations.{key}")
        mode = _choose(t.get("mode", "add"), OBSERVATION_MODES, f"observations.{key}.mode")
        name = t.get("name")
        if not name or name == "???" or name.strip("/") != name or "//" in name:
            raise ValueError(f"observations.{key}.name must be 'group/key', got {name!r}")
        params = plain(t.get("params") or {})
        skip = 2 if mode == "modify" else 1
        _check_params(func, params, f"observations.{key}", skip=skip, env=env)
        group = check_group(t.get("group", "policy"), f"observations.{key}.group")
        terms.append((key, func, mode, name, params, group))
    return terms


def build_reward_terms(
    rewards: Mapping[str, Any] | None, env: SimState
) -> list[tuple[str, Any, str, float, dict[str, Any]]]:
    """The reward terms, in config order: ``(key, func, mode, weight, params)`` each."""
    terms = []
    for key, term in (rewards or {}).items():
        t = as_dict(term)
        func = REWARDS.get(t["func"], f"rewards.{key}")
        mode = _choose(t.get("mode", "add"), REWARD_MODES, f"rewards.{key}.mode")
        params = plain(t.get("params") or {})
        _check_params(func, params, f"rewards.{key}", skip=1, env=env)
        weight = t.get("weight", 1.0)
        Number().check(weight, f"rewards.{key}.weight")
        terms.append((key, func, mode, float(weight), params))
    return terms
