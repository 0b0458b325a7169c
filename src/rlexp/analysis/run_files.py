"""What ``rlexp runs`` and ``rlexp compare`` read from one run dir, through ``rlexp.files.safe_read``:
its checked JSON files, its config (flattened) and its overrides. What cannot be used is left out and added to the caller's ``problems`` as
``"file: why"``, for one warning line per run."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rlexp.files import safe_read


def read_checked(run_dir: Path, name: str, problems: list[str], fields: dict) -> dict[str, Any]:
    """A JSON file of the run dir as checked by ``safe_read`` ({} and a problem when it is bad)."""
    try:
        return safe_read.read_checked(run_dir / name, fields)
    except safe_read.Unreadable as exc:
        problems.append(f"{name}: {exc}")
        return {}


def flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    """A nested config mapping as ``{dotted.key: leaf}`` (lists are leaves)."""
    if not isinstance(tree, dict):
        return {prefix[:-1]: tree} if prefix else {}
    out: dict[str, Any] = {}
    for key, value in tree.items():
        out.update(
            flatten(value, f"{prefix}{key}.")
            if isinstance(value, dict)
            else {f"{prefix}{key}": value}
        )
    return out


def read_config(run_dir: Path, problems: list[str] | None = None) -> dict[str, Any]:
    """The run's resolved ``config.yaml`` (else Hydra's ``.hydra/config.yaml``), flattened; what
    cannot be read is added to ``problems``."""
    problems = problems if problems is not None else []
    for name in ("config.yaml", ".hydra/config.yaml"):
        try:
            cfg = safe_read.load_yaml(run_dir / name)
        except safe_read.Unreadable as exc:
            problems.append(f"{name}: {exc}")
            continue
        if isinstance(cfg, dict):
            return flatten(cfg)
        if cfg is not None:
            problems.append(f"{name}: a {type(cfg).__name__}, not a mapping")
    return {}


def read_overrides(run_dir: Path, problems: list[str] | None = None) -> list[str]:
    """``.hydra/overrides.yaml`` ([] when missing; [] and a problem when it is not a list of
    overrides)."""
    try:
        return safe_read.read_overrides(run_dir / ".hydra" / "overrides.yaml")
    except safe_read.Unreadable as exc:
        if problems is not None:
            problems.append(f".hydra/overrides.yaml: {exc}")
        return []
