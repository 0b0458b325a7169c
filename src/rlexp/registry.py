"""Looking up a function a config names: a registered name, or a dotted path inside an allowlist of
modules (so a config file cannot import arbitrary code). Events and hooks both resolve this way."""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any


def choices_hint(value: str, choices: Sequence[str]) -> str:
    """``; choose from [...]`` and the closest choice, for an error message."""
    close = difflib.get_close_matches(value, list(choices), n=1)
    return f"; choose from {sorted(choices)}" + (f"; did you mean {close[0]!r}?" if close else "")


def resolve(
    name: str,
    where: str,
    registry: Mapping[str, Callable[..., Any]],
    allowed: Sequence[str],
    what: str,
    how_to_register: str,
) -> Callable[..., Any]:
    """``registry[name]``, or the object at dotted path ``name`` inside a module of ``allowed``;
    a ValueError naming ``<where>.func`` otherwise (``what``: "event function", "hook")."""
    if name in registry:
        return registry[name]
    if "." in name:
        if not any(name.startswith(p) for p in allowed):
            raise ValueError(
                f"{where}.func={name!r}: dotted paths must be inside {list(allowed)} "
                f"(a config may not import arbitrary code); {how_to_register}"
            )
        module, _, attr = name.rpartition(".")
        try:
            return getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as exc:
            raise ValueError(f"{where}.func={name!r} cannot be imported: {exc}") from exc
    raise ValueError(
        f"{where}.func={name!r} is not a known {what}" + choices_hint(name, list(registry))
    )
