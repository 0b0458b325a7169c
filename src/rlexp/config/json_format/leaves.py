"""RootConfig leaves: a RootConfig-shaped dict flattened to dotted leaves (``flatten``), nested back
(``nest``) and overlaid (``_overlay``), and ``_Mapped``, the leaves the two files set."""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any


def _dataclass_of(tp: Any) -> type | None:
    """The dataclass in a field type (``X``, ``X | None``), else None."""
    if dataclasses.is_dataclass(tp):
        return tp
    for arg in typing.get_args(tp):
        if dataclasses.is_dataclass(arg):
            return arg
    return None


def flatten(node: dict[str, Any], cls: type, prefix: str = "") -> dict[str, Any]:
    """Dotted leaves of a RootConfig-shaped dict: nested schema dataclasses are opened, every other
    field (numbers, lists, the term dicts) is one leaf, compared and replaced whole."""
    from rlexp.config.schema import VARIANTS

    hints = typing.get_type_hints(cls)
    out: dict[str, Any] = {}
    for key, value in node.items():
        sub = _dataclass_of(hints.get(key))
        if sub is not None and not prefix and key in VARIANTS:
            # the schema its name names; a partial section (the rlexp section's) without a name:
            # the group's first (nested sections it lacks stay whole leaves, which replace whole)
            variants = VARIANTS[key]
            name = value.get("name") if isinstance(value, dict) else None
            sub = variants.get(name, next(iter(variants.values())))
        if sub is not None and isinstance(value, dict):
            out.update(flatten(value, sub, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def nest(flat: dict[str, Any]) -> dict[str, Any]:
    """The inverse of ``flatten``."""
    out: dict[str, Any] = {}
    for dotted, value in flat.items():
        *parents, last = dotted.split(".")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[last] = value
    return out


def _overlay(flat: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """``flat`` with the leaves of ``new`` set; a leaf replaces whatever lay above or below it."""
    out = dict(flat)
    for key, value in new.items():
        for old in list(out):
            if old.startswith(key + ".") or key.startswith(old + "."):
                del out[old]
        out[key] = value
    return out


@dataclass
class _Mapped:
    """What the two files say, as RootConfig leaves, plus what to tell the user."""

    env_group: str = ""  # conf/env group of the task ("" for a Gymnasium id without one)
    env_base: dict[str, Any] = field(default_factory=dict)  # env.* leaves of conf/env/<group>.yaml
    leaves: dict[str, Any] = field(default_factory=dict)  # dotted RootConfig leaves the files set
    # leaves whose value is the task YAML's dict with the file's entries added: the YAML's part
    yaml_parts: dict[str, dict[str, Any]] = field(default_factory=dict)
    not_applicable: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    action_dim: int | None = None
    groups: dict[str, str] = field(default_factory=dict)  # policy / algorithm group options
