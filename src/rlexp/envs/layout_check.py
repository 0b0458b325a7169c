"""A checkpoint's or an export's recorded observation layout compared with the env's: the same
vector must mean the same things (parts, groups, kept entries), or one line says what changed."""

from __future__ import annotations

from typing import Any


def check_layout(saved: dict[str, Any] | None, env: Any, what: str) -> None:
    """ValueError when ``saved`` (an observation layout a checkpoint or export recorded) is not the
    layout of ``env``'s observations: the same vector would mean other things."""
    base = env
    while hasattr(base, "base_env"):
        base = base.base_env
    layout = getattr(base, "obs_layout", None)
    if saved is None or layout is None:
        return
    current = layout.record()
    if _parts_of(saved) != _parts_of(current):
        have = [_part_name(p) for p in saved.get("parts", [])]
        now = [_part_name(p) for p in current["parts"]]
        raise ValueError(
            f"{what} was made for observations flattened as {have} ({saved.get('dim')} values); "
            f"the env now gives {now} ({current['dim']} values): the observation space changed"
        )


def _part_name(part: dict[str, Any]) -> str:
    """A recorded part as a message names it: its key, and the entries kept where it keeps some."""
    name = part.get("key") or "(root)"
    return f"{name} entries {part['indices']}" if part.get("indices") else name


def _parts_of(record: dict[str, Any]) -> list[dict[str, Any]]:
    """A layout record's parts, a missing ``group`` read as ``"policy"`` (records made before
    observation groups have none; new ones write it only when it is not ``"policy"``)."""
    return [{"group": "policy", **p} if isinstance(p, dict) else p for p in record.get("parts", [])]
