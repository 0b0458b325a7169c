"""The replay buffer on disk: chunk files of the rows added between two checkpoints, and the
manifest (in the checkpoint) that says which chunks hold the buffer.

A chunk holds the transitions with global indices ``[start, stop)`` (the n-th transition ever added
has global index n; it sits at ring position ``n % capacity``). It is written once, atomically
(``rlexp.files.fsutil.atomic_write``), and never changed. A chunk is read like any checkpoint
file (issue #29, items 7-8): a regular file, no larger than its rows can be, every tensor it
declares checked against the manifest's layout before torch materialises anything
(``rlexp.checkpoints.scan``), ``weights_only``, then every field checked. What fails is one line
naming the file (``ReplayFileError``), never a traceback.
"""

from __future__ import annotations

import math
import os
import re
import secrets
import stat
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from rlexp.checkpoints.scan import ScanError, scan
from rlexp.files.fsutil import atomic_write

CHUNK_FORMAT = "rlexp-replay-chunk-v1"
MANIFEST_FORMAT = "rlexp-replay-v1"
#: What a chunk file's name must be: a manifest naming anything else (``../x``) is refused.
CHUNK_NAME = re.compile(r"chunk-(\d{12})-(\d{12})-[0-9a-f]{8}\.pt")
#: torch's zip framing beside the rows: headers, ``data.pkl``, 64-byte alignment per member.
_FRAMING_BYTES = 1 << 16
_PER_MEMBER_BYTES = 1 << 12
#: Transitions a buffer may hold (and a global index may reach): far past any run.
MAX_ROWS = 1 << 40
_DTYPES = {
    str(d): d
    for d in (torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.uint8)
    + (torch.int8, torch.int16, torch.int32, torch.int64, torch.bool)
}


class ReplayFileError(ValueError):
    """A chunk file or a manifest that cannot be used; the message names which and why."""


Layout = list[tuple[tuple[str, ...], str, tuple[int, ...]]]


def layout_of(rows: TensorDictBase) -> Layout:
    """Each stored entry's key, dtype and shape per row, sorted by key."""
    out = []
    for key in rows.keys(include_nested=True, leaves_only=True):
        parts = (key,) if isinstance(key, str) else tuple(key)
        value = rows.get(key)
        out.append((parts, str(value.dtype), tuple(value.shape[rows.batch_dims :])))
    return sorted(out)


def layout_text(layout: Layout) -> str:
    return ", ".join(f"{'.'.join(k)}: {d.removeprefix('torch.')}{list(s)}" for k, d, s in layout)


def row_bytes(layout: Layout) -> int:
    """The bytes one transition takes."""
    return sum(
        math.prod(s) * torch.empty((), dtype=_DTYPES[d]).element_size() for _, d, s in layout
    )


def chunk_name(start: int, stop: int) -> str:
    """A new chunk's file name: its rows, and a random tag (a run resumed from an older checkpoint
    writes the same rows again, perhaps differently: never over a file another checkpoint needs)."""
    return f"chunk-{start:012d}-{stop:012d}-{secrets.token_hex(4)}.pt"


def write_chunk(directory: Path, rows: TensorDictBase, start: int) -> dict[str, Any]:
    """Write ``rows`` (global indices ``start, start+1, ...``) as a new chunk; its manifest entry."""
    stop = start + rows.batch_size[0]
    path = Path(directory) / chunk_name(start, stop)
    data = {
        "format": CHUNK_FORMAT,
        "start": start,
        "stop": stop,
        "rows": {".".join(k): rows.get(k).contiguous() for k, _, _ in layout_of(rows)},
    }

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            torch.save(data, f)

    directory.mkdir(parents=True, exist_ok=True)
    try:
        atomic_write(path, write)
    except RuntimeError as exc:  # torch's writer reports a full disk as a RuntimeError
        raise OSError(f"writing replay chunk {path} failed: {str(exc).splitlines()[0]}") from None
    return {"file": path.name, "start": start, "stop": stop}


def read_chunk(directory: Path, entry: Mapping[str, Any], layout: Layout) -> TensorDict:
    """The rows of the chunk ``entry`` names, checked against ``layout``; ``ReplayFileError``
    naming the file for anything that is not the chunk the manifest expects."""
    path = Path(directory) / entry["file"]
    rows = entry["stop"] - entry["start"]
    try:
        return _read_chunk(path, entry, layout, rows)
    except ReplayFileError as exc:
        raise ReplayFileError(f"replay chunk {str(path)!r} {exc}") from None


def _read_chunk(path: Path, entry: Mapping[str, Any], layout: Layout, rows: int) -> TensorDict:
    try:
        info = os.stat(path)
    except OSError as exc:
        raise ReplayFileError(
            f"cannot be read ({exc.strerror or exc}): the checkpoint needs it"
        ) from None
    if not stat.S_ISREG(info.st_mode):
        raise ReplayFileError("is not a regular file")
    limit = rows * row_bytes(layout) + _FRAMING_BYTES + _PER_MEMBER_BYTES * len(layout)
    if info.st_size > limit:
        raise ReplayFileError(
            f"is {info.st_size} bytes; {rows} rows of its layout take at most {limit}"
        )
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        try:
            refs = scan(f, size)
        except ScanError as exc:
            raise ReplayFileError(f"is unreadable ({exc})") from None
        _check_declared(refs, layout, rows)
        f.seek(0)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                data = torch.load(f, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise ReplayFileError(f"is unreadable (corrupt: {str(exc)[:160]})") from None
    return _checked_rows(data, entry, layout, rows)


def _check_declared(refs: list, layout: Layout, rows: int) -> None:
    """Every tensor the file declares is one of the layout's, of its dtype and ``rows`` long."""
    expected = {"rows." + ".".join(k): (_DTYPES[d], (rows, *s)) for k, d, s in layout}
    for ref in refs:
        want = expected.get(ref.where)
        if want is None:
            raise ReplayFileError(f"holds a tensor {ref.where!r} the buffer does not store")
        if ref.storage.dtype != want[0] or tuple(ref.size) != want[1]:
            raise ReplayFileError(
                f"declares {ref.where} as {ref.storage.dtype} {list(ref.size)}; "
                f"the manifest expects {want[0]} {list(want[1])}"
            )


def _checked_rows(data: Any, entry: Mapping[str, Any], layout: Layout, rows: int) -> TensorDict:
    if not isinstance(data, dict) or data.get("format") != CHUNK_FORMAT:
        raise ReplayFileError(f"is not a replay chunk (format {CHUNK_FORMAT!r})")
    if data.get("start") != entry["start"] or data.get("stop") != entry["stop"]:
        raise ReplayFileError(
            f"holds rows [{data.get('start')!r}, {data.get('stop')!r}); the manifest expects "
            f"[{entry['start']}, {entry['stop']})"
        )
    stored = data.get("rows")
    names = {".".join(k) for k, _, _ in layout}
    if not isinstance(stored, dict) or set(stored) != names:
        found = sorted(stored) if isinstance(stored, dict) else type(stored).__name__
        raise ReplayFileError(f"holds entries {found}; the manifest expects {sorted(names)}")
    out = TensorDict({}, batch_size=[rows])
    for key, dtype, shape in layout:
        value = stored[".".join(key)]
        if (
            not isinstance(value, torch.Tensor)
            or str(value.dtype) != dtype
            or tuple(value.shape) != (rows, *shape)
        ):
            raise ReplayFileError(f"entry {'.'.join(key)} is not {dtype} {[rows, *shape]}")
        out.set(key, value)
    return out


# ----- the manifest: every field checked before a load uses it ---------------------------------


def _int(value: Any, field: str, low: int, high: int) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        raise ReplayFileError(
            f"replay.{field}={str(value)[:40]}; expected an int in [{low}, {high}]"
        )
    return value


def check_layout(value: Any) -> Layout:
    """The manifest's layout as ``layout_of`` makes it, or ``ReplayFileError``."""
    if not isinstance(value, list | tuple) or len(value) > 1024:
        raise ReplayFileError("replay.layout is not a list of entries")
    out = []
    for item in value:
        ok = isinstance(item, list | tuple) and len(item) == 3
        key, dtype, shape = item if ok else (None, None, None)
        ok = ok and isinstance(key, list | tuple) and key and all(isinstance(k, str) for k in key)
        ok = ok and dtype in _DTYPES and isinstance(shape, list | tuple) and len(shape) <= 8
        ok = ok and all(
            isinstance(s, int) and not isinstance(s, bool) and 0 <= s < 1 << 31 for s in shape
        )
        if not ok:
            raise ReplayFileError(
                f"replay.layout entry {str(item)[:80]} is not (key, dtype, shape)"
            )
        out.append((tuple(key), dtype, tuple(shape)))
    return sorted(out)


def check_chunks(value: Any, written: int, capacity: int) -> list[dict[str, Any]]:
    """The chunk entries: valid file names, ordered, together exactly the rows the buffer holds
    (the last ``min(written, capacity)`` global indices)."""
    if not isinstance(value, list | tuple):
        raise ReplayFileError("replay.chunks is not a list")
    chunks = []
    for item in value:
        if not isinstance(item, Mapping) or not isinstance(item.get("file"), str):
            raise ReplayFileError(f"replay.chunks entry {str(item)[:80]} names no file")
        if not CHUNK_NAME.fullmatch(item["file"]):
            raise ReplayFileError(f"replay.chunks names {item['file'][:80]!r}, not a chunk file")
        start = _int(item.get("start"), "chunks.start", 0, MAX_ROWS)
        stop = _int(item.get("stop"), "chunks.stop", start + 1, MAX_ROWS)
        chunks.append({"file": item["file"], "start": start, "stop": stop})
    first = written - min(written, capacity)
    at = chunks[0]["start"] if chunks else first
    for c in chunks:
        if c["start"] != at:
            raise ReplayFileError(
                f"replay.chunks do not follow each other: {c['file']} starts at {c['start']}, "
                f"expected {at}"
            )
        at = c["stop"]
    if (chunks and (chunks[0]["start"] > first or chunks[0]["stop"] <= first)) or at != written:
        raise ReplayFileError(
            f"replay.chunks hold rows up to {at}, starting "
            f"{chunks[0]['start'] if chunks else at}; the buffer holds [{first}, {written})"
        )
    return chunks


def check_saved(value: Any) -> dict[str, list[str]]:
    """The chunk names of each save not yet released (tag -> names)."""
    if not isinstance(value, Mapping) or len(value) > 10_000:
        raise ReplayFileError("replay.saved is not a dict of tag -> chunk names")
    out = {}
    for tag, names in value.items():
        if not isinstance(tag, str) or not isinstance(names, list | tuple):
            raise ReplayFileError(f"replay.saved[{str(tag)[:40]!r}] is not a list of chunk names")
        if not all(isinstance(n, str) and CHUNK_NAME.fullmatch(n) for n in names):
            raise ReplayFileError(f"replay.saved[{tag[:40]!r}] names a file that is no chunk")
        out[tag] = list(names)
    return out


def check_generator(value: Any) -> torch.Tensor:
    """A CPU ``torch.Generator``'s state: a uint8 vector as long as torch's."""
    size = torch.Generator().get_state().numel()
    if not isinstance(value, torch.Tensor) or value.dtype != torch.uint8 or value.shape != (size,):
        shown = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
        raise ReplayFileError(f"replay.generator is {shown}; expected a uint8 tensor [{size}]")
    return value


def check_pending(value: Any, layout: Layout, n_step: int) -> dict | None:
    """The n-step steps that wait for their window: ``valid`` [E, <n] and each entry of the
    layout (less ``steps_to_next_obs``) of the same leading shape."""
    if value is None:
        return None
    valid = value.get("valid") if isinstance(value, Mapping) else None
    if not isinstance(valid, torch.Tensor) or valid.dtype != torch.bool or valid.dim() != 2:
        raise ReplayFileError("replay.pending.valid is not a bool tensor [num_envs, steps]")
    if valid.shape[1] > n_step - 1:
        raise ReplayFileError(f"replay.pending holds {valid.shape[1]} steps; n_step={n_step}")
    steps = value.get("steps")
    expected = {k: (d, s) for k, d, s in layout if k != ("steps_to_next_obs",)}
    found: dict[tuple[str, ...], Any] = {}
    stack = [((), steps)]
    while stack:
        prefix, node = stack.pop()
        if not isinstance(node, Mapping) or len(prefix) > 8:
            raise ReplayFileError(f"replay.pending.steps.{'.'.join(prefix)} is not a dict")
        for k, v in node.items():
            if isinstance(v, torch.Tensor):
                found[(*prefix, k)] = v
            else:
                stack.append(((*prefix, k), v))
    if set(found) != set(expected):
        raise ReplayFileError("replay.pending.steps does not hold the buffer's entries")
    for key, (dtype, shape) in expected.items():
        t = found[key]
        if str(t.dtype) != dtype or tuple(t.shape) != (*valid.shape, *shape):
            raise ReplayFileError(f"replay.pending.steps.{'.'.join(key)} is not {dtype} {shape}")
    return value


# ----- where a checkpoint's chunks are --------------------------------------------------------


def replay_manifests(ckpt: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The replay manifests in a checkpoint (a trainer state): its own, and that of the state of
    an eval round in flight (a resume may write that state as best.pt or its step's checkpoint)."""
    out = []
    states = [ckpt]
    flight = ckpt.get("eval_in_flight")
    if isinstance(flight, Mapping) and isinstance(flight.get("state"), Mapping):
        states.append(flight["state"])
    for state in states:
        algorithm = state.get("algorithm")
        manifest = algorithm.get("replay") if isinstance(algorithm, Mapping) else None
        if isinstance(manifest, dict):
            out.append(manifest)
    return out


def chunk_names(manifest: Mapping[str, Any]) -> list[str]:
    """The chunk files a manifest names (entries that name none are skipped: the load refuses them)."""
    chunks = manifest.get("chunks")
    if not isinstance(chunks, list | tuple):
        return []
    return [c["file"] for c in chunks if isinstance(c, Mapping) and isinstance(c.get("file"), str)]


def locate_chunks(ckpt: dict[str, Any], path: Path) -> None:
    """Before a resume from the checkpoint file ``path``: find the folder that holds every chunk
    its manifests name, its run dir's ``replay/`` (``path`` in ``checkpoints/`` or beside
    ``replay/``), and record it in each manifest (``directory``: the load links those chunks into
    the resumed run's own folder, so it never deletes another run's). ``ReplayFileError`` naming
    the first chunk missing: a checkpoint whose rows are gone is unusable, as a corrupt file is."""
    path = Path(path)
    places = list(dict.fromkeys([path.parent.parent / "replay", path.parent / "replay"]))
    for manifest in replay_manifests(ckpt):
        manifest.pop("directory", None)  # only ever this function's: never the file's own say
        names = chunk_names(manifest)
        if not names:
            continue
        found = next((d for d in places if all((d / n).is_file() for n in names)), None)
        if found is None:
            missing = next(n for n in names if not (places[0] / n).is_file())
            raise ReplayFileError(
                f"its replay buffer's chunk {missing} is not in {' or '.join(map(str, places))} "
                "(deleted, or the checkpoint was copied without its run dir's replay/ folder)"
            )
        manifest["directory"] = str(found)


def adopt_chunks(source: Path, directory: Path, names: list[str]) -> None:
    """Put the chunks ``names`` of another run's folder ``source`` into ``directory``: a hard
    link (no copy; the other run's file is never changed nor deleted) or, across filesystems, a
    copy; each appears under its name at once (one rename)."""
    if Path(source).resolve() == Path(directory).resolve():
        return
    directory.mkdir(parents=True, exist_ok=True)
    for name in names:
        if not CHUNK_NAME.fullmatch(name):
            raise ReplayFileError(f"replay.chunks names {name[:80]!r}, not a chunk file")
        if (directory / name).is_file():
            continue
        src = Path(source) / name

        def put(tmp: Path, src: Path = src) -> None:
            tmp.unlink()  # atomic_write's empty temporary file, replaced by the link
            try:
                os.link(src, tmp)
            except OSError:  # another filesystem, or none with hard links
                with open(src, "rb") as fin, open(tmp, "wb") as fout:
                    while block := fin.read(1 << 20):
                        fout.write(block)

        try:
            atomic_write(directory / name, put)
        except OSError as exc:
            raise ReplayFileError(
                f"replay chunk {str(src)!r} cannot be read ({exc.strerror or exc}): the "
                "checkpoint needs it"
            ) from None
