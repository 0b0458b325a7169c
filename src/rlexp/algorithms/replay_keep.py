"""Which replay chunks the checkpoints on disk still name (SAC, TD3): what a commit must keep.

A chunk may be deleted only when no checkpoint a run could still resume from names it: the step
checkpoints ``trainer.keep_last`` leaves, ``best.pt``, and the eval round in flight that a
checkpoint holds (its state may become best.pt or its step's checkpoint on resume). The folder is
the truth, not the run's memory of what it wrote: a run resumed from an older checkpoint, or one
whose ``keep_last`` changed, finds newer or older files there that it never wrote. Each file's
chunk names are read once per version of the file (its inode, size and mtime); the checkpoint the
run just wrote is known without reading it.
"""

from __future__ import annotations

import logging
import stat
from pathlib import Path
from typing import Any

from rlexp.algorithms.replay_files import chunk_names, replay_manifests

log = logging.getLogger(__name__)


class ChunkKeeper:
    """The chunk names of the checkpoints in a folder, remembered per version of each file."""

    def __init__(self) -> None:
        self._known: dict[tuple[str, int, int, int], frozenset[str]] = {}

    @staticmethod
    def _version(path: Path) -> tuple[str, int, int, int] | None:
        try:
            info = path.stat()
        except OSError:
            return None
        if not stat.S_ISREG(info.st_mode):
            return None
        return (path.name, info.st_ino, info.st_size, info.st_mtime_ns)

    def note(self, path: Path, state: dict[str, Any]) -> None:
        """``state`` was just written to ``path``: its names, without reading the file back."""
        version = self._version(Path(path))
        if version is not None:
            self._known[version] = frozenset(_names(state))

    def named(self, directory: Path) -> set[str] | None:
        """Every chunk a checkpoint file in ``directory`` names (``corrupt/`` is not looked in);
        None when a file could not be read (then nothing may be deleted this time). A file that
        is no usable checkpoint names nothing: no resume can use its chunks."""
        from rlexp.checkpoints.files import load_checkpoint_file

        names: set[str] = set()
        seen = {}
        for path in sorted(Path(directory).glob("*.pt")):
            version = self._version(path)
            if version is None:
                continue
            if version not in self._known:
                try:
                    self._known[version] = frozenset(_names(load_checkpoint_file(path, "read")))
                except ValueError as exc:  # corrupt: a resume skips it too
                    log.debug("replay: %s names no chunks (%s)", path, exc)
                    self._known[version] = frozenset()
                except OSError as exc:
                    log.warning("replay: %s cannot be read (%s): no chunk deleted", path, exc)
                    return None
            seen[version] = self._known[version]
            names |= seen[version]
        self._known = seen  # versions no longer on disk are forgotten
        return names


def _names(state: dict[str, Any]) -> set[str]:
    return {n for manifest in replay_manifests(state) for n in chunk_names(manifest)}
