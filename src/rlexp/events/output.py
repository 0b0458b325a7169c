"""Where the built-in events write: a folder inside the run dir, files written through a temporary file.

Every file an event writes stays inside the run dir (``save_path`` is a folder under it; an absolute
folder only with ``allow_outside_run_dir: true``), checked when the config is validated
(``check_save_path``) and again when the file is written (``output_dir``).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rlexp.config.native_task import Flag, OrNull, SavePath
from rlexp.events.manager import EventContext
from rlexp.files.fsutil import atomic_write


def save_params(default: str) -> dict[str, Any]:
    """The rules of ``save_path`` / ``allow_outside_run_dir`` for an event writing into ``default``."""
    return {
        "save_path": OrNull(SavePath(), f"{default}/ in the run dir"),
        "allow_outside_run_dir": Flag(),
    }


def check_save_path(params: dict[str, Any], where: str) -> None:
    """An absolute ``save_path`` writes outside the run dir: only with an explicit opt-in, and the
    opt-in needs the absolute folder it is for."""
    save_path, allow = params.get("save_path"), params.get("allow_outside_run_dir", False)
    absolute = save_path is not None and os.path.isabs(save_path)
    if absolute and not allow:
        raise ValueError(
            f"{where}.params.save_path={save_path!r} is outside the run dir; give a folder relative "
            f"to the run dir (e.g. 'videos'), or set {where}.params.allow_outside_run_dir=true to "
            "write there on purpose"
        )
    if allow and not absolute:
        raise ValueError(
            f"{where}.params.allow_outside_run_dir=true needs an absolute save_path (the folder "
            f"outside the run dir); got save_path={save_path!r}"
        )


def output_dir(
    ctx: EventContext, save_path: str | None, default: str, allow_outside_run_dir: bool = False
) -> Path:
    """The folder an event writes into, created: ``<run_dir>/<save_path or default>``, which must
    still be inside the run dir once ``..`` and symlinks are resolved; an absolute ``save_path``
    only with ``allow_outside_run_dir``."""
    event = ctx.event or "event"
    if save_path is not None and os.path.isabs(save_path):
        if not allow_outside_run_dir:
            raise ValueError(
                f"{event}.params.save_path={save_path!r} is outside the run dir "
                "(allow_outside_run_dir is not set)"
            )
        out = Path(save_path)
        out.mkdir(parents=True, exist_ok=True)
        return out
    if ctx.run_dir is None:
        raise ValueError(f"{event}: no run dir to write into")
    root = Path(ctx.run_dir).resolve()
    out = root / (save_path or default)
    for _ in range(2):  # before creating it, and after (a part created meanwhile may be a link)
        real = out.resolve()
        if real != root and root not in real.parents:
            raise ValueError(
                f"{event}.params.save_path={save_path or default!r} resolves to {real}, outside "
                f"the run dir {root} (a symlink?); nothing was written"
            )
        out.mkdir(parents=True, exist_ok=True)
    return out


def write_new_file(path: Path, write: Callable[[Path], None]) -> None:
    """Write ``path`` through a temporary file created in its folder (never an existing file or
    link) and renamed over it: a link at ``path`` is replaced, not followed, and a killed run
    leaves no half-written file under the final name."""
    atomic_write(path, write, keep_suffix=True)  # the writers choose the format by suffix
