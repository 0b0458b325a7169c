"""Typed schema of a native (batched MuJoCo) task: the term lists of our users' task files, and the
rules that term and event parameters are checked with (``check_params``).

The names mirror the JSON task format (``gym_config``) so that the JSON loader maps one onto the other
key by key: ``events``, ``observations``, ``rewards``, ``actions``, ``extensions``, plus ``scene`` for
the parts of the file that shape the MJCF rebuild (cube size / mass / start, initial joint positions).
"""

from __future__ import annotations

import difflib
import math
import numbers
import os
import re
from dataclasses import dataclass, field
from typing import Any

from rlexp.config.rules import MAX_NAME, is_safe_name


@dataclass
class EventTermConfig:
    """One event term: ``func(env, env_ids, **params)`` fired in ``mode``."""

    func: str = "???"  # registered event function name
    mode: str = "reset"  # startup | reset | interval | step | trigger
    interval_step: int = 1  # for mode=interval: fire every this many calls
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class ObservationTermConfig:
    """One observation term; its output is stored under ``name`` ("group/key")."""

    func: str = "???"  # registered observation function name
    mode: str = "add"  # add | modify
    name: str = "???"  # "group/key" in the observation dict (flattened with sorted keys)
    params: dict[str, Any] = field(default_factory=dict)
    # the observation group the entry belongs to (what policy.actor/critic.observations select):
    # policy (the actor's, by default) | critic (privileged: the critic's only, by default) | ...
    group: str = "policy"


#: An observation group's name: a Python identifier (``policy``, ``critic``, ``privileged_2``).
GROUP_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def check_group(value: Any, where: str) -> str:
    """An observation term's ``group`` (``where``: its dotted key); one line if it is no name."""
    if not isinstance(value, str) or not GROUP_NAME.fullmatch(value):
        raise ValueError(
            f"{where}={_show(value)} must be an observation group name (letters, digits and _, "
            "not starting with a digit), e.g. 'policy' (the actor's) or 'critic' (privileged)"
        )
    return value


@dataclass
class RewardTermConfig:
    """One reward term; the env's reward is the sum of ``weight * func(...)``."""

    func: str = "???"  # registered reward function name
    mode: str = "add"  # add | replace
    weight: float = 1.0  # multiplies the term
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class ActionTermConfig:
    """The action term that maps the policy's action to actuator targets."""

    func: str = "DeltaQposTerm"  # registered action term name
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class NativeTaskConfig:
    """A native task: which MJCF scene (``task``) plus its term configuration."""

    task: str = "???"  # registered native task: push_cube | cart_pole
    events: dict[str, EventTermConfig] = field(default_factory=dict)
    observations: dict[str, ObservationTermConfig] = field(default_factory=dict)
    rewards: dict[str, RewardTermConfig] = field(default_factory=dict)
    actions: dict[str, ActionTermConfig] = field(default_factory=dict)
    extensions: dict[str, Any] = field(default_factory=dict)  # free values, e.g. success_threshold
    scene: dict[str, Any] = field(
        default_factory=dict
    )  # scene overrides (cube size/mass/init_pos, init_qpos)


# --- parameter rules -------------------------------------------------------------------------------
# Every parameter of a built-in term or event has a rule: its type, length and order, range, and
# (given the env) the names and indices that must exist. ``check_params`` applies them and names the
# dotted key in every error; docs/events.md and docs/native_tasks.md list them (``rule.text``).

#: A name that becomes part of a file name: one safe path component (as trainer.exp_name).


def plain(value: Any) -> Any:
    """Params with nested mappings / sequences as plain dicts and lists (OmegaConf containers too)."""
    if hasattr(value, "items"):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)) or type(value).__name__ == "ListConfig":
        return [plain(v) for v in value]
    return value


def _show(value: Any) -> str:
    return repr(plain(value))


def _number(value: Any, where: str, integer: bool = False) -> float:
    """``value`` as a finite number (bools are not numbers here); TypeError / ValueError naming ``where``."""
    kind = "an integer" if integer else "a number"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{where}={_show(value)} must be {kind}")
    if integer and not isinstance(value, numbers.Integral):
        raise TypeError(f"{where}={_show(value)} must be {kind}")
    if not math.isfinite(value):
        raise ValueError(f"{where}={_show(value)} must be a finite number")
    return float(value)


def _bounds_text(gt: float | None, ge: float | None, lt: float | None, le: float | None) -> str:
    parts = []
    if gt is not None:
        parts.append(f"> {gt:g}")
    if ge is not None:
        parts.append(f">= {ge:g}")
    if lt is not None:
        parts.append(f"< {lt:g}")
    if le is not None:
        parts.append(f"<= {le:g}")
    return " and ".join(parts)


def _in_bounds(x: float, gt: float | None, ge: float | None, lt: float | None, le: float | None):
    return (
        (gt is None or x > gt)
        and (ge is None or x >= ge)
        and (lt is None or x < lt)
        and (le is None or x <= le)
    )


class ParamRule:
    """How one parameter is checked. ``check`` raises TypeError (wrong type / shape) or ValueError
    (out of range), naming ``where`` and the value; with ``env`` (a built native env) it also checks
    the names and indices the value refers to. ``text`` completes "must be ..." (docs tables)."""

    text = ""

    def check(self, value: Any, where: str, env: Any = None) -> None:
        raise NotImplementedError


@dataclass(frozen=True)
class Number(ParamRule):
    """A finite number (``integer``: a whole one) within the given bounds."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    integer: bool = False
    note: str = ""  # why the bound, appended to the error and the docs

    @property
    def text(self) -> str:  # type: ignore[override]
        kind = "an integer" if self.integer else "a finite number"
        bounds = _bounds_text(self.gt, self.ge, self.lt, self.le)
        return f"{kind}{' ' + bounds if bounds else ''}{self.note}"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        x = _number(value, where, self.integer)
        if not _in_bounds(x, self.gt, self.ge, self.lt, self.le):
            raise ValueError(f"{where}={_show(value)} must be {self.text}")


@dataclass(frozen=True)
class Flag(ParamRule):
    text = "true or false"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, bool):
            raise TypeError(f"{where}={_show(value)} must be true or false")


@dataclass(frozen=True)
class Text(ParamRule):
    """A non-empty string, one of ``choices`` if given."""

    choices: tuple[str, ...] = ()

    @property
    def text(self) -> str:  # type: ignore[override]
        return f"one of {list(self.choices)}" if self.choices else "a non-empty string"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, str) or not value:
            raise TypeError(f"{where}={_show(value)} must be {self.text}")
        if self.choices and value not in self.choices:
            raise ValueError(
                f"{where}={value!r} must be {self.text}" + _did_you_mean(value, self.choices)
            )


@dataclass(frozen=True)
class FileName(ParamRule):
    """One safe file-name component: it becomes part of a file the run writes."""

    text = (
        "a safe file name: letters, digits and . _ = + - (starting with a letter or digit, "
        f"no '/' or '..', at most {MAX_NAME} characters)"
    )

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, str):
            raise TypeError(f"{where}={_show(value)} must be {self.text}")
        if not is_safe_name(value):
            raise ValueError(f"{where}={value!r} must be {self.text}")


@dataclass(frozen=True)
class SavePath(ParamRule):
    """A folder under the run dir: relative, not climbing out of it with ``..``. An absolute folder
    only with the event's explicit ``allow_outside_run_dir: true`` (checked by the event)."""

    text = (
        "a folder relative to the run dir that stays inside it (no leading '..'); an absolute "
        "folder only with allow_outside_run_dir: true"
    )

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, str) or not value.strip():
            raise TypeError(f"{where}={_show(value)} must be {self.text}")
        if "\0" in value:
            raise ValueError(f"{where}={value!r} contains a NUL byte")
        if os.path.isabs(value):
            return  # the event decides (allow_outside_run_dir)
        norm = os.path.normpath(value)
        if norm == ".." or norm.startswith(".." + os.sep):
            raise ValueError(f"{where}={value!r} leaves the run dir; give a folder inside it")


def _numbers(value: Any, where: str, n: int, shape: str, integer: bool = False) -> list[float]:
    if not isinstance(value, (list, tuple)):
        raise TypeError(f"{where}={_show(value)} must be {shape}")
    if len(value) != n:
        raise ValueError(f"{where}={_show(value)} must be {shape} ({n} values, got {len(value)})")
    return [_number(v, f"{where}[{i}]", integer) for i, v in enumerate(value)]


@dataclass(frozen=True)
class Vector(ParamRule):
    """A fixed-length list of finite numbers, named in order (``names``); the elements named in
    ``bounded`` (all of them if empty) must satisfy the bounds."""

    names: tuple[str, ...] = ("x", "y", "z")
    gt: float | None = None
    ge: float | None = None
    le: float | None = None
    integer: bool = False
    bounded: tuple[str, ...] = ()
    note: str = ""

    @property
    def shape(self) -> str:
        return "[" + ", ".join(self.names) + "]"

    @property
    def text(self) -> str:  # type: ignore[override]
        kind = "integers" if self.integer else "finite numbers"
        bounds = _bounds_text(self.gt, self.ge, None, self.le)
        if bounds:
            who = ", ".join(self.bounded) if self.bounded else "each"
            bounds = f", {who} {bounds}"
        return f"{self.shape} ({kind}{bounds}{'; ' + self.note if self.note else ''})"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        xs = _numbers(value, where, len(self.names), self.shape, self.integer)
        for name, x in zip(self.names, xs, strict=True):
            if (not self.bounded or name in self.bounded) and not _in_bounds(
                x, self.gt, self.ge, None, self.le
            ):
                raise ValueError(f"{where}={_show(value)} must be {self.text}: {name}={x:g}")


@dataclass(frozen=True)
class Interval(ParamRule):
    """``[low, high]``: two finite numbers, low <= high (``strict``: low < high), low within bounds."""

    gt: float | None = None
    ge: float | None = None
    strict: bool = False
    note: str = ""

    @property
    def text(self) -> str:  # type: ignore[override]
        order = "low < high" if self.strict else "low <= high"
        bound = _bounds_text(self.gt, self.ge, None, None)
        return f"[low, high] with {order}" + (f", low {bound}" if bound else "") + self.note

    def check(self, value: Any, where: str, env: Any = None) -> None:
        low, high = _numbers(value, where, 2, "[low, high]")
        if low > high or (self.strict and low == high):
            why = f"low {low:g} > high {high:g}" if low > high else "low == high"
        elif not _in_bounds(low, self.gt, self.ge, None, None):
            why = f"low {low:g} is not {_bounds_text(self.gt, self.ge, None, None)}"
        else:
            return
        raise ValueError(f"{where}={_show(value)} must be {self.text}: {why}")


@dataclass(frozen=True)
class Box(ParamRule):
    """``[[x, y, z], [x, y, z]]``: the low and high corners of a box, low <= high on every axis."""

    text = "[[x, y, z], [x, y, z]] (finite numbers, low <= high on every axis)"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise TypeError(f"{where}={_show(value)} must be {self.text}")
        low = _numbers(value[0], f"{where}[0]", 3, "[x, y, z]")
        high = _numbers(value[1], f"{where}[1]", 3, "[x, y, z]")
        for axis, lo, hi in zip("xyz", low, high, strict=True):
            if lo > hi:
                raise ValueError(
                    f"{where}={_show(value)} must be {self.text}: {axis} low {lo:g} > high {hi:g}"
                )


@dataclass(frozen=True)
class JointIds(ParamRule):
    """Distinct robot joint indices (into the task's robot joints)."""

    text = "a non-empty list of distinct robot joint indices [i, ...] (0 <= i < the task's robot joints)"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, (list, tuple)) or not value:
            raise TypeError(f"{where}={_show(value)} must be {self.text}")
        ids = [int(_number(v, f"{where}[{i}]", integer=True)) for i, v in enumerate(value)]
        if len(set(ids)) != len(ids):
            raise ValueError(f"{where}={_show(value)} has repeated joint indices")
        n = getattr(env, "num_robot_joints", None)
        bad = [i for i in ids if i < 0 or (n is not None and i >= n)]
        if bad:
            joints = (
                f" (the task has {n}: {list(env.task_spec.robot_joints)})" if n is not None else ""
            )
            raise ValueError(
                f"{where}={_show(value)}: joint index {bad[0]} is out of range{joints}"
            )


@dataclass(frozen=True)
class Entity(ParamRule):
    """``{uid: <object>}``: a rigid object of the task's scene."""

    text = "{uid: the uid of a rigid object of the task}"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, dict) or not isinstance(value.get("uid"), str):
            raise TypeError(f"{where}={_show(value)} must be {self.text}")
        extra = sorted(set(value) - {"uid"})
        if extra:
            raise KeyError(
                f"{where}.{extra[0]} is not a key of an entity config; it has only 'uid'"
            )
        objects = getattr(getattr(env, "task_spec", None), "objects", None)
        if objects is not None and value["uid"] not in objects:
            raise KeyError(
                f"{where}.uid={value['uid']!r} is not a rigid object of {env.task_spec.name}; "
                f"choose from {sorted(objects)}" + _did_you_mean(value["uid"], objects)
            )


@dataclass(frozen=True)
class Part(ParamRule):
    """A control part of the task (``arm``, ``hand``...)."""

    text = "a control part of the task"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if not isinstance(value, str) or not value:
            raise TypeError(f"{where}={_show(value)} must be {self.text}")
        parts = getattr(getattr(env, "task_spec", None), "parts", None)
        if parts is not None and value not in parts:
            raise KeyError(
                f"{where}={value!r} is not a control part of {env.task_spec.name}; choose from "
                f"{sorted(parts)}" + _did_you_mean(value, parts)
            )


@dataclass(frozen=True)
class OrNull(ParamRule):
    """``null`` (meaning ``meaning``) or a value of ``rule``."""

    rule: ParamRule = field(default_factory=Number)
    meaning: str = "the default"

    @property
    def text(self) -> str:  # type: ignore[override]
        return f"null ({self.meaning}) or {self.rule.text}"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        if value is not None:
            self.rule.check(value, where, env)


class Unchecked(ParamRule):
    """Any value: a parameter of a function registered without rules (its name is still checked)."""

    text = "any value (a function without rules: checked against its signature only)"

    def check(self, value: Any, where: str, env: Any = None) -> None:
        return


def _did_you_mean(value: str, choices: Any) -> str:
    close = difflib.get_close_matches(str(value), [str(c) for c in choices], n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def check_params(
    func: str,
    params: Any,
    rules: dict[str, ParamRule],
    where: str,
    required: tuple[str, ...] | list[str] = (),
    env: Any = None,
) -> dict[str, Any]:
    """Check ``params`` of ``func`` against ``rules`` (``where``: the dotted key of the params, e.g.
    ``events.train.dr.params``); returns them as plain dicts and lists. Unknown names are a
    TypeError naming the key with the closest known one; a missing required one too."""
    params = plain(params) if params is not None else {}
    if not isinstance(params, dict):
        raise TypeError(f"{where}={_show(params)} must be a mapping of parameter names to values")
    unknown = [k for k in params if k not in rules]
    if unknown:
        raise TypeError(
            f"{where}.{unknown[0]}: unknown parameter(s) {unknown} for {func}; it accepts "
            f"{list(rules)}" + _did_you_mean(unknown[0], rules)
        )
    missing = [k for k in required if k not in params]
    if missing:
        raise TypeError(f"{where}: {func} needs parameter(s) {missing}")
    for key, value in params.items():
        rules[key].check(value, f"{where}.{key}", env)
    return params
