"""Typed reads of one file's JSON values (``_File``): each value checked for its kind, range and
choices, with errors that name the file, the dotted key, the value and the fix."""

from __future__ import annotations

import difflib
import json
from typing import Any

from rlexp.config.validate import ConfigError

_REQUIRED = object()


def _show(value: Any) -> str:
    text = json.dumps(value) if not isinstance(value, str) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


class _File:
    """Typed reads from one file's JSON, with errors that name the file and the dotted key."""

    def __init__(self, shown: str) -> None:
        self.shown = shown

    def error(self, msg: str) -> ConfigError:
        return ConfigError(f"{self.shown}: {msg}")

    def obj(self, value: Any, where: str, known: tuple[str, ...] | None = None) -> dict[str, Any]:
        """``value`` as an object whose keys are all in ``known``."""
        if not isinstance(value, dict):
            raise self.error(f"{where or 'the file'} must be an object {{...}}, got {_show(value)}")
        if known is not None:
            for key in value:
                if key not in known:
                    msg = f"unknown key {_join(where, key)!r}"
                    close = difflib.get_close_matches(key, known, n=1)
                    if close:
                        msg += f"; did you mean {_join(where, close[0])!r}?"
                    msg += f" ({where or 'the file'} accepts {sorted(known)})"
                    raise self.error(msg)
        return value

    def get(
        self,
        d: dict[str, Any],
        key: str,
        where: str,
        kind: str,
        default: Any = _REQUIRED,
        low: float | None = None,
        high: float | None = None,
        choices: tuple[str, ...] | None = None,
        positive: bool = False,
    ) -> Any:
        """``d[key]`` checked against ``kind`` (int, number, bool, str, object, list, ints, numbers),
        the range [low, high] (``positive``: > 0) and ``choices``."""
        dotted = _join(where, key)
        if key not in d:
            if default is _REQUIRED:
                raise self.error(f"{dotted} is required")
            return default
        return self.check(d[key], dotted, kind, low, high, choices, positive)

    def check(
        self,
        value: Any,
        dotted: str,
        kind: str,
        low: float | None = None,
        high: float | None = None,
        choices: tuple[str, ...] | None = None,
        positive: bool = False,
    ) -> Any:
        bad = self.error(f"{dotted}={_show(value)} must be {_KIND_TEXT[kind]}")
        if kind == "int":
            if isinstance(value, bool) or not isinstance(value, int):
                raise bad
        elif kind == "number":
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise bad
        elif kind == "bool":
            if not isinstance(value, bool):
                raise bad
        elif kind == "str":
            if not isinstance(value, str) or not value:
                raise bad
        elif kind == "object":
            if not isinstance(value, dict):
                raise bad
        elif kind == "list":
            if not isinstance(value, list):
                raise bad
        elif kind in ("ints", "numbers"):
            if not isinstance(value, list):
                raise bad
            for i, item in enumerate(value):
                self.check(
                    item,
                    f"{dotted}[{i}]",
                    "int" if kind == "ints" else "number",
                    low,
                    high,
                    None,
                    positive,
                )
            return [float(v) for v in value] if kind == "numbers" else value
        if kind in ("int", "number"):
            if positive and value <= 0:
                raise self.error(f"{dotted}={_show(value)} is out of range: must be > 0")
            if (low is not None and value < low) or (high is not None and value > high):
                rng = f">= {low:g}" if high is None else f"in [{low:g}, {high:g}]"
                raise self.error(f"{dotted}={_show(value)} is out of range: must be {rng}")
        if choices is not None and value not in choices:
            msg = f"{dotted}={_show(value)}: choose from {list(choices)}"
            close = difflib.get_close_matches(str(value), choices, n=1)
            raise self.error(msg + (f"; did you mean {close[0]!r}?" if close else ""))
        return float(value) if kind == "number" else value


_KIND_TEXT = {
    "int": "an integer",
    "number": "a number",
    "bool": "true or false",
    "str": "a non-empty string",
    "object": "an object {...}",
    "list": "a list [...]",
    "ints": "a list of integers",
    "numbers": "a list of numbers",
}
