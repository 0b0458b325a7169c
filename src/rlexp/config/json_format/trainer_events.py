"""The train file's ``trainer.events`` (train / eval): each event checked against rlexp's event
registry (format aliases resolved, record_video's parameters checked) and mapped to an
EventTermConfig dict."""

from __future__ import annotations

import difflib
from typing import Any

from rlexp.config.json_format.typed_reads import _File, _show

#: Event function names of the format -> rlexp's registered event functions.
EVENT_ALIASES = {"record_camera_data_async": "record_video"}
#: Parameters of record_video the format uses (the registered function may accept more).
RECORD_VIDEO_PARAMS = ("name", "resolution", "eye", "target", "up", "intrinsics", "save_path")
EVENT_TERM_KEYS = ("func", "mode", "interval_step", "params")


def _registered_events() -> dict[str, Any]:
    """rlexp's event registry with the built-in events loaded."""
    from rlexp.events import builtin  # noqa: F401  (registers the built-in events)
    from rlexp.events.manager import EVENT_FUNCS

    return EVENT_FUNCS


def _event_names() -> list[str]:
    """Registered event functions, plus record_video (the format's eval video) and its alias."""
    return sorted({"record_video", *EVENT_ALIASES, *_registered_events()})


def _record_video_params() -> set[str]:
    """Parameters record_video accepts: the format's, plus keyword ones of the registered function
    (for a class: of its ``__call__`` and ``finalize``)."""
    import inspect

    params = set(RECORD_VIDEO_PARAMS)
    func = _registered_events().get("record_video")
    if func is None:
        return params
    targets = (
        [func] if not isinstance(func, type) else [func.__call__, getattr(func, "finalize", None)]
    )
    for target in targets:
        if target is None:
            continue
        for p in inspect.signature(target).parameters.values():
            if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and p.name not in (
                "self",
                "ctx",
            ):
                params.add(p.name)
    return params


def _events(tf: _File, events: dict[str, Any], where: str) -> dict[str, Any]:
    """The trainer's train / eval events as EventTermConfig dicts (format aliases resolved)."""
    from rlexp.events import MODES

    known = _event_names()
    out = {}
    for name, ev in events.items():
        w = f"{where}.{name}"
        ev = tf.obj(ev, w, EVENT_TERM_KEYS)
        func = tf.get(ev, "func", w, "str")
        if func not in known and "." not in func:
            close = difflib.get_close_matches(func, known, n=1)
            raise tf.error(
                f"{w}.func={func!r} is not a known event function; choose from {known}"
                + (f"; did you mean {close[0]!r}?" if close else "")
            )
        if "." in func:
            from rlexp.events.manager import resolve_event_func

            try:
                resolve_event_func(func, w)
            except ValueError as exc:
                raise tf.error(str(exc)) from None
        func = EVENT_ALIASES.get(func, func)
        params = tf.get(ev, "params", w, "object", {})
        if func == "record_video":
            _check_record_video(tf, params, f"{w}.params")
        out[name] = {
            "func": func,
            "mode": tf.get(ev, "mode", w, "str", "reset", choices=MODES),
            "interval_step": tf.get(ev, "interval_step", w, "int", 1, low=1),
            "params": params,
        }
    return out


def _check_record_video(tf: _File, params: dict[str, Any], where: str) -> None:
    known = tuple(sorted(_record_video_params()))
    tf.obj(params, where, known)
    shapes = {
        "resolution": ("ints", 2),
        "eye": ("numbers", 3),
        "target": ("numbers", 3),
        "up": ("numbers", 3),
        "intrinsics": ("numbers", 4),
    }
    for key, (kind, n) in shapes.items():
        if key in params:
            value = tf.get(params, key, where, kind, positive=key == "resolution")
            if len(value) != n:
                raise tf.error(f"{where}.{key}={_show(params[key])} must have {n} values")
    for key in ("name", "save_path"):
        if key in params:
            tf.get(params, key, where, "str")
