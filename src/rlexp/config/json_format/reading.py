"""Reading an experiment file: the text of a regular UTF-8 file of a sane size, parsed strictly into a
JSON object (no duplicate keys, no NaN/Infinity, no deeper nesting than MAX_DEPTH); every refusal is
a ConfigError that names the file (and the line where there is one)."""

from __future__ import annotations

import json
import os
import re
import stat
from pathlib import Path
from typing import Any

from rlexp.config.validate import ConfigError

#: Experiment files are a few KiB; anything near this is not one (and would only cost memory).
MAX_FILE_BYTES = 4 * 2**20
#: Nesting the files may use (theirs need ~6): deeper JSON is refused before it is parsed, as the
#: parser, OmegaConf and Hydra recurse once per level.
MAX_DEPTH = 32


class _DuplicateKey(ValueError):
    pass


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON")


def read_json(path: Path, shown: str) -> dict[str, Any]:
    """Strictly parsed JSON object (no duplicate keys, no NaN/Infinity); errors give line and column."""
    text = _read_text(path, shown)
    line = _too_deep(text)
    if line is not None:
        raise ConfigError(
            f"{shown}: JSON nested more than {MAX_DEPTH} levels deep (line {line}); an experiment "
            "file needs a handful"
        )
    try:
        data = json.loads(text, object_pairs_hook=_no_duplicates, parse_constant=_no_constant)
    except json.JSONDecodeError as exc:
        raise ConfigError(
            f"{shown}: invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
    except _DuplicateKey as exc:
        line = _line_of(text, exc.args[0])
        raise ConfigError(f"{shown}: duplicate key {exc.args[0]!r}{line}; keep one") from None
    except ValueError as exc:
        raise ConfigError(f"{shown}: invalid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(
            f"{shown}: the file must hold a JSON object {{...}}, got {type(data).__name__}"
        )
    return data


_FILE_KINDS = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _read_text(path: Path, shown: str) -> str:
    """The file's text, refusing what is not a regular UTF-8 file of a sane size (a FIFO is opened
    without blocking, so that a pipe with no writer cannot hang the run)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise ConfigError(f"{shown}: no such file") from None
    except OSError as exc:
        raise ConfigError(f"{shown}: cannot be read ({exc.strerror})") from None
    except ValueError as exc:  # a NUL byte in the path
        raise ConfigError(f"{shown}: cannot be read ({exc})") from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise ConfigError(
                f"{shown}: is a directory; give the train file in it "
                f"(e.g. {os.path.join(shown, 'train_config.json')})"
            )
        if not stat.S_ISREG(st.st_mode):
            kind = next((name for test, name in _FILE_KINDS if test(st.st_mode)), "a special file")
            raise ConfigError(f"{shown}: is not a regular file ({kind}); give a JSON file")
        if st.st_size > MAX_FILE_BYTES:
            raise ConfigError(_too_big(shown, st.st_size))
        with open(fd, "rb", closefd=False) as f:
            data = f.read(MAX_FILE_BYTES + 1)
        if len(data) > MAX_FILE_BYTES:  # the size stat gave was wrong (a file still growing)
            raise ConfigError(_too_big(shown, len(data)))
    except OSError as exc:
        raise ConfigError(f"{shown}: cannot be read ({exc.strerror})") from None
    finally:
        os.close(fd)
    try:
        return data.decode("utf-8-sig")  # a byte-order mark (Windows editors) is not an error
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise ConfigError(
            f"{shown}: is not UTF-8 text (byte 0x{data[exc.start]:02x} at line {line}); "
            "save it as UTF-8"
        ) from None


def _too_big(shown: str, size: int) -> str:
    return f"{shown}: is {size} bytes; an experiment file may hold at most {MAX_FILE_BYTES // 2**20} MiB"


#: A JSON string (escaped quotes included; an unterminated one runs to the end, so that the scan
#: stays linear): brackets inside one are data, not nesting.
_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"?', re.DOTALL)


def _too_deep(text: str) -> int | None:
    """The line where ``text`` nests deeper than MAX_DEPTH, else None. Checked before parsing: the
    parser (and everything after it that walks the values) recurses once per level."""
    bare = _JSON_STRING.sub('""', text)  # JSON strings hold no raw newline: lines stay the same
    if bare.count("[") + bare.count("{") <= MAX_DEPTH:
        return None
    depth = 0
    for m in re.finditer(r"[\[\]{}]", bare):
        depth += 1 if m.group() in "[{" else -1
        if depth > MAX_DEPTH:
            return bare.count("\n", 0, m.start()) + 1
    return None


def _line_of(text: str, key: str) -> str:
    """' (line N)' of the second occurrence of ``"key"``, for duplicate-key errors."""
    hits = [m.start() for m in re.finditer(re.escape(json.dumps(key)) + r"\s*:", text)]
    return f" (line {text.count(chr(10), 0, hits[1]) + 1})" if len(hits) > 1 else ""
