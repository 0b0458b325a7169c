"""Trainer hooks: user code at fixed points of the training loop (docs/hooks.md).

A hook sees a read-only :class:`HookState` and acts only through a :class:`HookControl`: log a
scalar, request a stop, or set a hyperparameter the algorithm declares mutable. It never holds the
Trainer. The points, in the order the Trainer fires them in one iteration:

``train_start`` (also after a resume: ``state.resumed``), ``rollout_end`` (``state.batch``),
``update_end`` (``state.losses``), ``log`` (``state.metrics``: what is about to be written; a hook
may add keys with ``control.log``), ``eval_end`` (``state.eval_metrics``), ``checkpoint``
(``state.checkpoint``), and once at the end ``train_end`` (``state.status``: finished,
stopped_early, pruned, interrupted or failed).

Stops and hyperparameter changes are *decisions*: they are queued and applied by the Trainer at two
points every rank reaches together (before the update, and at the end of the iteration), with rank
0's decisions sent to every rank, so a distributed run changes and stops in step.

A config names a hook by its registered name, or by a dotted path inside an allowlist of modules
(``rlexp.hooks.`` plus whatever Python code adds with ``allow_hook_module``), as for events. A
registered *function* is called as ``func(state, control, **params)`` at the points it was
registered for; a registered *class* is instantiated once with ``**params`` and its instance called
as ``hook(state, control)``; it may keep state (``state_dict`` / ``load_state_dict``, checkpointed).
"""

from __future__ import annotations

import difflib
import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from rlexp.common.registry import resolve
from rlexp.config.native_task import ParamRule, Unchecked, check_params, plain

#: The hook points, in the order the Trainer fires them.
POINTS = ("train_start", "rollout_end", "update_end", "log", "eval_end", "checkpoint", "train_end")
#: How a run can end, as ``train_end`` tells it.
END_STATUSES = ("finished", "stopped_early", "pruned", "interrupted", "failed")
#: The statuses a hook's stop may end a run with: a result either way (exit 0, a checkpoint);
#: ``pruned``: an Optuna pruner decided (``rlexp.hooks.optuna_prune``).
STOP_STATUSES = ("stopped_early", "pruned")

HOOK_FUNCS: dict[str, Callable[..., Any]] = {}
_ALLOWED_MODULES: list[str] = ["rlexp.hooks."]


def register_hook(
    name: str,
    *,
    points: tuple[str, ...] = POINTS,
    params: dict[str, ParamRule] | None = None,
    required: tuple[str, ...] = (),
) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorator: make a function or class available to configs as ``func: <name>``.

    ``points``: where it is called (default: every point; it can read ``state.point``);
    ``params``: a rule per parameter (without them the signature is the check); ``required``: the
    parameters a config must give."""
    unknown = [p for p in points if p not in POINTS]
    if unknown:
        raise ValueError(f"hook {name!r}: unknown points {unknown}; choose from {list(POINTS)}")

    def deco(func: Callable[..., Any]) -> Callable[..., Any]:
        func.POINTS = tuple(points)  # type: ignore[attr-defined]
        if params is not None:
            func.PARAMS = dict(params)  # type: ignore[attr-defined]
            func.REQUIRED = tuple(required)  # type: ignore[attr-defined]
        HOOK_FUNCS[name] = func
        return func

    return deco


def allow_hook_module(prefix: str) -> None:
    """Let configs name hooks by dotted path under ``prefix`` (from Python code only)."""
    prefix = prefix if prefix.endswith(".") else prefix + "."
    if prefix not in _ALLOWED_MODULES:
        _ALLOWED_MODULES.append(prefix)


@dataclass(frozen=True)
class HookState:
    """What a hook sees at a point (read-only; mappings are views)."""

    point: str
    global_step: int
    iteration: int  # updates done so far
    total_steps: int  # the run's budget in env steps
    run_dir: Path
    rank: int = 0
    world_size: int = 1
    resumed: bool = False  # train_start: the run continues from a checkpoint
    losses: Mapping[str, float] = field(default_factory=dict)  # latest update's losses
    metrics: Mapping[str, float] = field(default_factory=dict)  # latest logged training metrics
    eval_metrics: Mapping[str, float] = field(default_factory=dict)  # latest evaluation
    hyperparameters: Mapping[str, float] = field(default_factory=dict)  # current mutable values
    batch: Any = None  # rollout_end: the rollout just collected [num_envs, T]
    checkpoint: Path | None = None  # checkpoint: the file just written
    status: str | None = None  # train_end: how the run ended (END_STATUSES)
    hook: str = ""  # the dotted config key of the hook being called (for its errors)


@dataclass
class Decisions:
    """What hooks decided in one stretch of the loop: applied together, the same on every rank."""

    stop: str | None = None  # the reason of the first stop request
    stop_status: str = "stopped_early"  # the status the run ends with (STOP_STATUSES)
    set: dict[str, float] = field(default_factory=dict)  # hyperparameter -> value (last wins)
    load: str | None = None  # a checkpoint whose training state replaces this run's (PBT's exploit)

    def empty(self) -> bool:
        return self.stop is None and not self.set and self.load is None


class HookControl:
    """What a hook may do. ``log`` adds a scalar to the metrics logged this iteration; ``request_stop``
    ends the run at the next safe point with a checkpoint and status ``stopped_early``; ``set``
    changes a mutable hyperparameter from the next update on."""

    def __init__(self, mutable: Mapping[str, float]) -> None:
        self._mutable = mutable
        self.decisions = Decisions()
        self.logged: dict[str, float] = {}
        self.where = ""

    def log(self, key: str, value: float) -> None:
        if not isinstance(key, str) or not key:
            raise ValueError(f"{self.where}: log key must be a non-empty string, got {key!r}")
        self.logged[key] = float(value)

    def request_stop(self, reason: str, status: str = "stopped_early") -> None:
        """Stop at the next safe point; ``status``: how the run ends (``pruned`` for a trial an
        Optuna pruner stopped)."""
        if status not in STOP_STATUSES:
            raise ValueError(f"{self.where}: stop status {status!r}; choose from {STOP_STATUSES}")
        if self.decisions.stop is None:
            self.decisions.stop = f"{reason} ({self.where})" if self.where else str(reason)
            self.decisions.stop_status = status

    def set(self, name: str, value: float) -> None:
        if name not in self._mutable:
            close = difflib.get_close_matches(name, list(self._mutable), n=1)
            raise ValueError(
                f"{self.where}: {name!r} is not a mutable hyperparameter; choose from "
                f"{sorted(self._mutable)}" + (f"; did you mean {close[0]!r}?" if close else "")
            )
        value = float(value)
        if value != value or value in (float("inf"), float("-inf")):
            raise ValueError(f"{self.where}: {name}={value} must be a finite number")
        self.decisions.set[name] = value

    def load_state(self, checkpoint: Path) -> None:
        """Replace this run's weights, optimiser and normaliser state with ``checkpoint``'s at the
        next safe point, before the hyperparameters set with it (PBT's exploit, rlexp.pbt); the
        run keeps its own step counters, envs and RNG."""
        self.decisions.load = str(checkpoint)


def resolve_hook_func(name: str, where: str) -> Callable[..., Any]:
    """A registered name, or a dotted path inside the allowlist."""
    return resolve(
        name,
        where,
        HOOK_FUNCS,
        _ALLOWED_MODULES,
        "hook",
        "register the hook with rlexp.hooks.register_hook or allow its module with "
        "allow_hook_module",
    )


def check_hook(func_name: str, params: Any, where: str) -> tuple[Callable[..., Any], dict]:
    """The hook's function and its params (plain), after checking both (``where``: hooks.<name>)."""
    func = resolve_hook_func(func_name, where)
    params = plain(params) if params is not None else {}
    if not isinstance(params, dict):
        raise TypeError(f"{where}.params={params!r} must be a mapping of parameter names to values")
    rules = getattr(func, "PARAMS", None)
    if rules is not None:
        check_params(func_name, params, rules, f"{where}.params", getattr(func, "REQUIRED", ()))
    else:
        _check_signature(func, func_name, params, where)
    extra = getattr(func, "check_params", None)
    if extra is not None:
        extra(params, where)
    return func, params


def _check_signature(func: Callable[..., Any], name: str, params: dict, where: str) -> None:
    """A hook without rules: its params must be keywords its constructor (class) or call (function)
    accepts, and give every keyword without a default."""
    target = func.__init__ if isinstance(func, type) else func
    try:
        sig = inspect.signature(target)
    except (TypeError, ValueError):
        return
    ps = list(sig.parameters.values())[1 if isinstance(func, type) else 2 :]
    if any(p.kind is p.VAR_KEYWORD for p in ps):
        return
    accepted = {
        p.name: p.default is p.empty
        for p in ps
        if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
    }
    rules = {k: Unchecked() for k in accepted}
    check_params(name, params, rules, f"{where}.params", [k for k, req in accepted.items() if req])


class HookManager:
    """Calls the configured hooks at each point, in config order, and collects their decisions."""

    def __init__(
        self,
        hooks: Mapping[str, Any],
        mutable: Mapping[str, float] = MappingProxyType({}),
        loader: Callable[[Path, Any], None] | None = None,
    ):
        self.hooks: list[tuple[str, tuple[str, ...], Callable[..., Any]]] = []
        self.control = HookControl(mutable)
        self.loader = loader  # applies ``load_state`` decisions: (checkpoint, algorithm)
        self.stop_status = "stopped_early"  # how a hook's stop ends the run: the first stop's
        self._stopped = False
        for name, cfg in hooks.items():
            where = f"hooks.{name}"
            func, params = check_hook(cfg.func, cfg.params, where)
            points = tuple(getattr(func, "POINTS", POINTS))
            if isinstance(func, type):
                call = func(**params)
            else:

                def call(state, control, _f=func, _p=params):
                    return _f(state, control, **_p)

            self.hooks.append((where, points, call))

    def __bool__(self) -> bool:
        return bool(self.hooks)

    def fire(self, point: str, state: HookState) -> None:
        """Call every hook registered for ``point`` (a hook's exception names the hook)."""
        for where, points, call in self.hooks:
            if point not in points:
                continue
            self.control.where = where
            try:
                call(_with(state, where), self.control)
            except ValueError as exc:
                raise HookError(f"{where} at {point}: {exc}") from exc
            finally:
                self.control.where = ""

    def take_logged(self) -> dict[str, float]:
        logged, self.control.logged = self.control.logged, {}
        return logged

    def apply(self, algorithm: Any, gather: Callable[[Any], list[Any]] | None = None) -> Decisions:
        """Take the decisions made since the last call and set their hyperparameters on
        ``algorithm``; distributed (``gather``: all_gather_object), rank 0's decisions for all."""
        decisions, self.control.decisions = self.control.decisions, Decisions()
        if gather is not None:
            decisions = gather(decisions)[0]
        if decisions.stop is not None and not self._stopped:
            self.stop_status, self._stopped = decisions.stop_status, True
        if decisions.load is not None and self.loader is not None:
            self.loader(Path(decisions.load), algorithm)
        for name, value in decisions.set.items():
            algorithm.set_hyperparameter(name, value)
        return decisions

    def state_dict(self) -> dict[str, Any]:
        return {
            where: call.state_dict() for where, _, call in self.hooks if hasattr(call, "state_dict")
        }

    def load_state_dict(self, sd: Mapping[str, Any]) -> None:
        for where, _, call in self.hooks:
            if where in sd and hasattr(call, "load_state_dict"):
                call.load_state_dict(sd[where])


class HookError(RuntimeError):
    """A hook raised: the message names the hook and the point."""


def _with(state: HookState, where: str) -> HookState:
    from dataclasses import replace

    return replace(state, hook=where)
