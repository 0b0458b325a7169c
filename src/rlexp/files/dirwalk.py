"""Finding run dirs in a tree (``outputs/``, ``multirun/``, a sweep dir), symlinks included.

Users link run dirs and date dirs into ``outputs/`` (a dir moved to another disk, a shared
results tree), so a symlink to a dir is followed like a dir. Each dir is visited once, by its
identity (device, inode): a symlink loop ends, and a run reached by two paths is found once, under
the path without a symlink when it has one (dirs reached through a symlink are walked after all
the others).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable
from pathlib import Path

#: ``wanted(dir, names in it)``: whether a dir is one the caller looks for.
Wanted = Callable[[Path, set[str]], bool]


def find_dirs(
    roots: Iterable[Path],
    wanted: Wanted,
    skip: Callable[[str], bool],
    inside_wanted: bool = False,
) -> list[Path]:
    """The dirs at or under ``roots`` that are ``wanted``, in the order found; subdirs whose name
    ``skip`` says are not entered, nor (unless ``inside_wanted``) the subdirs of a wanted dir.
    Unreadable dirs are passed over."""
    seen: set[tuple[int, int]] = set()
    found: list[Path] = []
    plain: deque[Path] = deque(Path(r) for r in roots)
    linked: deque[Path] = deque()  # reached through a symlink: walked after every plain dir
    while plain or linked:
        via_link = not plain
        here = linked.popleft() if via_link else plain.popleft()
        try:
            st = os.stat(here)
            if (st.st_dev, st.st_ino) in seen:
                continue  # a loop, or a dir already found by another path
            seen.add((st.st_dev, st.st_ino))
            with os.scandir(here) as it:
                entries = sorted(it, key=lambda e: e.name)
        except OSError:
            continue
        if wanted(here, {e.name for e in entries}):
            found.append(here)
            if not inside_wanted:
                continue
        for entry in entries:
            if skip(entry.name):
                continue
            try:
                is_dir, is_link = entry.is_dir(), entry.is_symlink()  # is_dir follows a symlink
            except OSError:
                continue
            if is_dir:
                (linked if via_link or is_link else plain).append(Path(entry.path))
    return found
