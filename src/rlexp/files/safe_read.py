"""Bounded, checked reading of the files in run dirs, for ``rlexp runs``, ``report`` and ``compare``.

Those commands read every run dir under a tree, so one damaged or hostile dir must cost one
warning, never a hang, a traceback or gigabytes for the listing of all the others. Every reader of
a run-dir file goes through here:

- regular files only: ``stat`` first, then ``open`` with ``O_NONBLOCK`` and ``fstat`` again (a FIFO
  would block ``open`` forever, a symlink to ``/dev/zero`` never ends, a dir is no file);
- at most ``LIMITS[name]`` bytes, and never past the size the file had when opened (a file being
  appended to ends where it was); ``metrics.jsonl`` line by line, each at most ``MAX_LINE`` bytes;
- JSON and YAML at most ``MAX_DEPTH`` deep; YAML without aliases (rlexp and Hydra never write one,
  and a 1 kB "billion laughs" expands into gigabytes in whoever walks it) and with safe tags only;
- the fields a command uses checked for type and range (``check_fields``): a step of -5, 10**400,
  1e308 or "abc", a pid that is a string, a list where an object belongs.

What fails raises ``Unreadable`` (a ``ValueError``) saying why in a few words.
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO

import yaml

#: Bytes read at most, per kind of file (a bigger one is "too large"); rlexp writes a few kB.
LIMITS = {
    "status.json": 1 << 20,
    "heartbeat.json": 1 << 20,
    "provenance.json": 1 << 20,
    "config.yaml": 4 << 20,
    "overrides.yaml": 1 << 20,
    "multirun.yaml": 4 << 20,
}
DEFAULT_LIMIT = 1 << 20
#: Nesting of JSON/YAML containers at most (configs are ~5 deep; Python's parsers recurse).
MAX_DEPTH = 64
#: Bytes of one ``metrics.jsonl`` line at most (a row is ~1 kB); a longer line is skipped unread.
MAX_LINE = 1 << 20
#: The largest step, budget or tick count taken as one (int64, as the checkpoints hold it).
MAX_INT = 2**63 - 1
#: Opening never blocks (FIFO), never takes a terminal, never leaks into a child.
_FLAGS = os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC
_KINDS = {
    stat.S_ISDIR: "a directory",
    stat.S_ISFIFO: "a FIFO",
    stat.S_ISCHR: "a character device",
    stat.S_ISBLK: "a block device",
    stat.S_ISSOCK: "a socket",
}


class Unreadable(ValueError):
    """A run-dir file that is there but cannot be used: why, in a few words."""


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS.items() if test(mode)), "not a regular file")


def _size(path: Path) -> int | None:
    """The size of regular file ``path``; None when there is none; Unreadable otherwise."""
    try:
        st = os.stat(path)  # follows a symlink: what it points to must be a regular file
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError as exc:
        raise Unreadable(f"not readable ({exc.strerror or exc})") from None
    if not stat.S_ISREG(st.st_mode):
        raise Unreadable(f"{_kind(st.st_mode)}, not a regular file")
    return st.st_size


@contextmanager
def open_regular(path: Path) -> Iterator[tuple[BinaryIO, int] | None]:
    """``(file, size at open)`` of a regular file, None when there is none; Unreadable when it is
    something else (checked again on the open file: it may have been swapped since the stat)."""
    if _size(path) is None:
        yield None
        return
    try:
        fd = os.open(path, _FLAGS)
    except (FileNotFoundError, NotADirectoryError):
        yield None
        return
    except OSError as exc:
        raise Unreadable(f"not readable ({exc.strerror or exc})") from None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise Unreadable(f"{_kind(st.st_mode)}, not a regular file")
        yield f, st.st_size


def read_bytes(path: Path, limit: int | None = None) -> bytes | None:
    """At most ``limit`` bytes (default: ``LIMITS`` of its name) of a regular file; None when
    there is none. Unreadable: not a regular file, not readable, or larger than ``limit``."""
    limit = limit if limit is not None else LIMITS.get(Path(path).name, DEFAULT_LIMIT)
    with open_regular(Path(path)) as opened:
        if opened is None:
            return None
        f, size = opened
        if size > limit:
            raise Unreadable(f"too large ({size} bytes; at most {limit} are read)")
        try:
            return f.read(min(size, limit))
        except OSError as exc:
            raise Unreadable(f"not readable ({exc.strerror or exc})") from None


def read_tail(path: Path, nbytes: int) -> tuple[bytes, int] | None:
    """(the last ``nbytes`` at most, the file's size) of a regular file; None when there is none."""
    with open_regular(Path(path)) as opened:
        if opened is None:
            return None
        f, size = opened
        try:
            f.seek(max(0, size - nbytes))
            return f.read(min(size, nbytes)), size
        except OSError as exc:
            raise Unreadable(f"not readable ({exc.strerror or exc})") from None


def iter_lines(f: BinaryIO, size: int, max_line: int = MAX_LINE) -> Iterator[bytes | None]:
    """The lines of an open file up to byte ``size`` (its size at open); None for a line longer
    than ``max_line`` (skipped without holding it: a 2 GB file of one line costs ``max_line``)."""
    left = size
    while left > 0:
        line = f.readline(min(max_line + 1, left))
        if not line:
            return
        left -= len(line)
        if len(line) <= max_line or line.endswith(b"\n"):
            yield line
            continue
        while left > 0 and not line.endswith(b"\n"):  # skip the rest of the long line
            line = f.readline(min(max_line, left))
            if not line:
                break
            left -= len(line)
        yield None


# -- parsing ---------------------------------------------------------------------------------------
def check_depth(value: Any, max_depth: int = MAX_DEPTH) -> Any:
    """``value`` if its containers nest at most ``max_depth`` deep (walked without recursion)."""
    stack = [(value, 1)] if isinstance(value, (dict, list)) else []
    while stack:
        node, depth = stack.pop()
        if depth > max_depth:
            raise Unreadable(f"nested more than {max_depth} deep")
        children = node.values() if isinstance(node, dict) else node
        stack += [(c, depth + 1) for c in children if isinstance(c, (dict, list))]
    return value


def parse_json(data: bytes | str) -> Any:
    """JSON text (bytes that are not UTF-8 are replaced), at most MAX_DEPTH deep."""
    text = data.decode("utf-8", errors="replace") if isinstance(data, bytes) else data
    try:
        value = json.loads(text)
    except RecursionError:
        raise Unreadable(f"nested more than {MAX_DEPTH} deep") from None
    except ValueError as exc:  # also an integer of more than 4300 digits
        raise Unreadable(f"not JSON ({str(exc).splitlines()[0][:80]})") from None
    return check_depth(value)


class _NoAliases:
    """A YAML loader mixin: refuses aliases, and nodes nested more than MAX_DEPTH deep, before
    anything is built (an alias makes one node reachable twice in the composed graph)."""

    def construct_document(self, node: yaml.Node) -> Any:
        seen: set[int] = set()
        stack = [(node, 1)]
        while stack:
            here, depth = stack.pop()
            if id(here) in seen:
                raise Unreadable("uses a YAML alias (*name), which rlexp never writes")
            seen.add(id(here))
            if isinstance(here, yaml.CollectionNode):
                if depth > MAX_DEPTH:
                    raise Unreadable(f"nested more than {MAX_DEPTH} deep")
                for item in here.value:  # nodes, or (key, value) pairs of nodes
                    for child in item if isinstance(item, tuple) else (item,):
                        stack.append((child, depth + 1))
        return super().construct_document(node)  # type: ignore[misc]


_SAFE = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
NoAliasLoader = type("NoAliasLoader", (_NoAliases, _SAFE), {})


def parse_yaml(data: bytes | str, loader: type | None = None) -> Any:
    """YAML text through ``loader`` (default: the safe loader) without aliases, at most MAX_DEPTH
    deep; a tag outside the safe set (``!!python/object``) is refused."""
    base = loader or _SAFE
    no_alias = NoAliasLoader if base is _SAFE else type("NoAlias", (_NoAliases, base), {})
    text = data.decode("utf-8", errors="replace") if isinstance(data, bytes) else data
    try:
        return yaml.load(text, Loader=no_alias)  # noqa: S506 (a safe loader)
    except Unreadable:
        raise
    except RecursionError:
        raise Unreadable(f"nested more than {MAX_DEPTH} deep") from None
    except (yaml.YAMLError, ValueError, TypeError, ArithmeticError) as exc:
        # ValueError: a tagged scalar its constructor refuses (!!float abc, a 13th month, an
        # integer of more than 4300 digits)
        raise Unreadable(f"not readable YAML ({str(exc).splitlines()[0][:80]})") from None


def load_json(path: Path, limit: int | None = None) -> Any:
    """A file's JSON (None when there is no file), read as ``read_bytes``, parsed as ``parse_json``."""
    data = read_bytes(path, limit)
    return None if data is None else parse_json(data)


def load_yaml(path: Path, limit: int | None = None, loader: type | None = None) -> Any:
    """A file's YAML (None when there is no file or it is empty), as ``parse_yaml``."""
    data = read_bytes(path, limit)
    return None if data is None else parse_yaml(data, loader)


# -- fields: type and range where they are used ----------------------------------------------------
#: A field check: "" when the value is good, else what is wrong with it.
Check = Callable[[Any], str]


def shown(value: Any, width: int = 40) -> str:
    """A value for a message, cut short (an int of 10**400 digits is shown by its size)."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 10**30:
        return f"an integer of {value.bit_length()} bits"
    text = repr(value)
    return text if len(text) <= width else text[: width - 3] + "..."


def whole(low: int = 0, high: int = MAX_INT) -> Check:
    """An integer in [low, high] (not a bool, not a float)."""

    def check(v: Any) -> str:
        if isinstance(v, bool) or not isinstance(v, int):
            return "is not a whole number"
        return "" if low <= v <= high else f"is out of range [{low}, {high}]"

    return check


def number(low: float = -math.inf, high: float = math.inf) -> Check:
    """A finite JSON number in [low, high]."""

    def check(v: Any) -> str:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return "is not a number"
        try:
            x = float(v)
        except OverflowError:
            return "is out of range"
        return "" if math.isfinite(x) and low <= x <= high else f"is out of range [{low}, {high}]"

    return check


def text(max_len: int = 256, pattern: str | None = None) -> Check:
    """A string of at most ``max_len`` characters (matching ``pattern`` when given)."""

    def check(v: Any) -> str:
        if not isinstance(v, str):
            return "is not a string"
        if len(v) > max_len:
            return f"is longer than {max_len} characters"
        return "" if pattern is None or re.fullmatch(pattern, v) else "is not a valid name"

    return check


def scores(v: Any) -> str:
    """An object of metric name -> number or null (an eval's results)."""
    if not isinstance(v, dict):
        return "is not an object"
    bad = next((k for k, x in v.items() if x is not None and number()(x) and not _nan(x)), None)
    return "" if bad is None else f"holds {bad!s:.40} = {shown(v[bad])}, not a number"


def _nan(x: Any) -> bool:
    """A NaN/Inf float: a legitimate eval result (non-finite returns are written as such)."""
    return isinstance(x, float) and not math.isfinite(x)


def strings(v: Any) -> str:
    """A list of strings."""
    if not isinstance(v, list):
        return "is not a list"
    return "" if all(isinstance(x, str) for x in v) else "holds an item that is not a string"


def mapping(v: Any) -> str:
    return "" if isinstance(v, dict) else "is not an object"


def check_fields(data: Any, fields: dict[str, Check]) -> dict[str, Any]:
    """``data`` when it is an object whose ``fields`` (when present and not null) pass their
    checks; Unreadable naming the first that does not."""
    if not isinstance(data, dict):
        names = {list: "an array", str: "a string", bool: "a boolean", type(None): "null"}
        raise Unreadable(f"{names.get(type(data), 'a number')}, not an object")
    for key, check in fields.items():
        value = data.get(key)
        why = check(value) if value is not None else ""
        if why:
            raise Unreadable(f"{key} {shown(value)} {why}")
    return data


# -- the files of a run dir ------------------------------------------------------------------------
_STATE = r"[a-z][a-z_]{0,31}"  # running, finished, stopped_early, ...
_PID = whole(1, 1 << 22)  # Linux's PID_MAX_LIMIT
_TIME = number(0, 1e11)  # epoch seconds (year 5138)
STATUS_FIELDS: dict[str, Check] = {
    "state": text(32, _STATE),
    "global_step": whole(),
    "final_eval": scores,
    "time": text(64),
    "pid": _PID,
    "host": text(),
}
HEARTBEAT_FIELDS: dict[str, Check] = {
    "host": text(),
    "pid": _PID,
    "pid_start_ticks": whole(),
    "boot_id": text(64),
    "interval_s": number(1e-3, 86400),
    "time": _TIME,
    "task": text(),
    "algorithm": text(),
    "global_step": whole(),
    "total": whole(),
    "best_metric": text(),
    "best": number(),
    "last_eval": scores,
    "stall_timeout_s": number(0, 1e9),
    "step_time": _TIME,
}
PROVENANCE_FIELDS: dict[str, Check] = {
    "start_time": text(64),
    "host": text(),
    "git_commit": text(64),
    "project": mapping,
    "argv": strings,
}


def read_checked(path: Path, fields: dict[str, Check]) -> dict[str, Any]:
    """A run-dir JSON file as an object whose ``fields`` passed their checks ({} when there is
    none); Unreadable saying why otherwise."""
    data = load_json(path)
    return {} if data is None else check_fields(data, fields)


def read_overrides(path: Path) -> list[str]:
    """``.hydra/overrides.yaml``: a list of ``key=value`` strings ([] when there is none). Plain
    ``- item`` lines (what Hydra writes) are read without the YAML parser."""
    data = read_bytes(path)
    if data is None:
        return []
    lines = data.decode("utf-8", errors="replace").splitlines()
    if all(ln.startswith("- ") and ln[2:3] not in "'\"&*!|>{[#%@`" for ln in lines):
        return [ln[2:].strip() for ln in lines]
    value = parse_yaml(data)
    if value is None:
        return []
    if not isinstance(value, list):
        raise Unreadable(f"a {type(value).__name__}, not a list of overrides")
    bad = next((x for x in value if isinstance(x, (dict, list))), None)
    if bad is not None:
        raise Unreadable(f"holds {shown(bad)}, not a key=value override")
    return [str(x) for x in value]
