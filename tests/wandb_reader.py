"""Reads an offline W&B run file (``run-*.wandb``: a LevelDB-style log of protobuf Records), so tests
can check what W&B itself wrote without a server."""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from pathlib import Path

_BLOCK = 32768
_HEADER = 7  # crc32 (4) + length (2) + type (1)


def read_records(path: str | Path) -> Iterator[bytes]:
    """The raw protobuf payloads, reassembled from FULL / FIRST / MIDDLE / LAST fragments."""
    data = Path(path).read_bytes()
    if data[:4] != b":W&B":
        raise ValueError(f"{path} is not a W&B run file")
    pos, buf = 7, b""
    while pos + _HEADER <= len(data):
        left = _BLOCK - (pos % _BLOCK)
        if left < _HEADER:
            pos += left
            continue
        _crc, length, rtype = struct.unpack("<IHB", data[pos : pos + _HEADER])
        if rtype == 0 and length == 0:  # block padding
            pos += left
            continue
        payload = data[pos + _HEADER : pos + _HEADER + length]
        pos += _HEADER + length
        if rtype == 1:
            yield payload
        elif rtype == 2:
            buf = payload
        elif rtype == 3:
            buf += payload
        elif rtype == 4:
            yield buf + payload
            buf = b""


def history(path: str | Path) -> list[dict]:
    """The ``wandb.log`` rows written to a ``run-*.wandb`` file."""
    from wandb.proto import wandb_internal_pb2 as pb

    rows = []
    for raw in read_records(path):
        rec = pb.Record()
        rec.ParseFromString(raw)
        if rec.WhichOneof("record_type") == "history":
            rows.append(
                {
                    (i.key or "/".join(i.nested_key)): json.loads(i.value_json)
                    for i in rec.history.item
                }
            )
    return rows


def run_info(path: str | Path) -> dict:
    """The run record of a ``run-*.wandb`` file: id, group, name, project."""
    from wandb.proto import wandb_internal_pb2 as pb

    for raw in read_records(path):
        rec = pb.Record()
        rec.ParseFromString(raw)
        if rec.WhichOneof("record_type") == "run":
            r = rec.run
            return {
                "id": r.run_id,
                "group": r.run_group,
                "name": r.display_name,
                "project": r.project,
            }
    raise ValueError(f"{path} has no run record")
