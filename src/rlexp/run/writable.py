"""Whether a run can write where it will write, tried on the real paths before anything trains.

A folder that cannot be created (a read-only ``outputs/``, a path through a regular file, a name
longer than the filesystem allows, a full disk) would otherwise surface as a traceback from Hydra
when it creates the run dir, or as a failure at the first checkpoint after an hour of training.
The checks here create the folder and a file whose path is as long as the longest one the run will
write (``checkpoints/.<exp_name>_step_<9 digits>.pt.tmp-<pid>``), write a byte, and remove it again:
a name the filesystem refuses (``ENAMETOOLONG``, a path over ``PATH_MAX``), a read-only mount, a
missing permission or a full disk fail here, as they would later (docs/faults.md).
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rlexp.files.fsutil import step_file_name, temp_path

#: The names a run gives its files under its run dir (rlexp.checkpoints.files, rlexp.run.rundir).
CHECKPOINTS = "checkpoints"
_PROBE = ".rlexp-write-test"


def checkpoint_temp_name(exp_name: str) -> str:
    """The temporary name of a step checkpoint (``rlexp.checkpoints.files.save_checkpoint`` writes through
    ``rlexp.files.fsutil.temp_path``), at the widest step the name has room for: the longest file name a
    run writes."""
    return temp_path(Path(step_file_name(exp_name, 999_999_999))).name


def run_dir_longest(exp_name: str) -> int:
    """Characters of the longest path a run writes below its run dir (``checkpoints/<temp>``)."""
    return len(f"{CHECKPOINTS}/{checkpoint_temp_name(exp_name)}")


def probe_dir(directory: str | Path, longest: int = 0, keep: bool = False) -> None:
    """Create ``directory`` (and its missing parents), then create, write and remove a file whose
    path below ``directory`` is ``longest`` characters long (at least a short probe name): the
    ``OSError`` a later write would meet (``filename``: the path that failed). The folders this
    call created are removed again unless ``keep`` (a check leaves nothing behind)."""
    target = Path(os.path.abspath(directory))
    created = _missing_parents(target)
    try:
        for attempt in (1, 2):
            try:
                os.makedirs(target, exist_ok=True)
                if not target.is_dir():
                    raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(target))
                _write_probe(target, longest)
                break
            except FileNotFoundError:  # another launch's check removed the folder it had made
                if attempt == 2:
                    raise
    except OSError:
        _remove_dirs(created)
        raise
    if not keep:
        _remove_dirs(created)


def _missing_parents(path: Path) -> list[Path]:
    """``path`` and its ancestors that do not exist yet, deepest first."""
    missing = []
    for p in (path, *path.parents):
        if os.path.lexists(p):
            break
        missing.append(p)
    return missing


def _write_probe(directory: Path, longest: int) -> None:
    """One byte into a new file of the given path length below ``directory``, then remove it."""
    name = f"{_PROBE}-{os.getpid()}"
    room = _limit(directory, "PC_NAME_MAX", 255)  # one name: never longer than a name may be
    name += "x" * max(0, min(longest, room) - len(name))
    path = directory / name
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.pwrite(fd, b"\0", 0)  # a full disk refuses a byte (an empty file needs no block)
        finally:
            os.close(fd)
            path.unlink(missing_ok=True)
    except OSError as exc:  # named by the folder: the probe's own name means nothing to a user
        raise OSError(exc.errno, exc.strerror, str(directory)) from None


def _limit(path: Path, name: str, default: int) -> int:
    """``os.pathconf`` of the nearest existing folder at or above ``path``."""
    for p in (path, *path.parents):
        try:
            return int(os.pathconf(p, name))
        except (OSError, ValueError):
            continue
    return default


def _remove_dirs(dirs: list[Path]) -> None:
    for d in dirs:  # deepest first; a folder something else wrote into meanwhile stays
        try:
            os.rmdir(d)
        except OSError:
            pass


def check_appendable(path: Path) -> None:
    """An existing file a run appends to or locks (its log, ``.rlexp.lock``) can be opened for
    writing; nothing is written and a missing file is fine (it will be created)."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND)
    except FileNotFoundError:
        return
    os.close(fd)


def describe(exc: OSError, what: str, path: Path, longest: int, fix: str) -> str:
    """One line for a failed probe of ``path``: what could not be written, where, why, the fix."""
    if exc.errno == errno.ENAMETOOLONG:
        name_max = _limit(Path(path), "PC_NAME_MAX", 255)
        longer = [n for n in Path(path).parts if len(os.fsencode(n)) > name_max]
        full = len(os.fsencode(os.path.abspath(path))) + 1 + longest
        why = (
            f"{exc.strerror}: a name in it has {len(os.fsencode(longer[0]))} bytes, this "
            f"filesystem allows {name_max}"
            if longer
            else f"{exc.strerror}: the run's checkpoints there would have paths of {full} bytes, "
            f"this filesystem allows {_limit(Path(path), 'PC_PATH_MAX', 4096) - 1}"
        )
    elif exc.errno in (errno.ENOTDIR, errno.EEXIST, errno.ENOENT) and _blocker(Path(path)):
        why = f"{_blocker(Path(path))} ({exc.strerror})"
    else:
        why = exc.strerror or str(exc)
    failed = str(exc.filename) if exc.filename is not None else ""
    probe = Path(failed).name.startswith(_PROBE)
    where = f" at {failed}" if failed and failed != str(path) and not probe else ""
    return f"{what} {path} cannot be written: {why}{where}; {fix}"


def _blocker(path: Path) -> str:
    """What in ``path`` is in the way of a folder (a file, a link to nothing), or ""."""
    for part in reversed([path, *Path(os.path.abspath(path)).parents]):
        if os.path.isdir(part) or not os.path.lexists(part):
            continue
        if os.path.islink(part):
            return f"{part} is a symlink to {os.readlink(part)}, which is not a folder"
        return f"{part} is a file, not a folder"
    return ""


def check_run_dir_writable(run_dir: Path, exp_name: str, log_name: str | None = None) -> None:
    """The run dir can be created and written at its longest path, and the files a run opens in
    place (its log, the lock) can be; ``OSError`` otherwise (``describe`` it)."""
    run_dir = Path(os.path.abspath(run_dir))
    probe_dir(run_dir, run_dir_longest(exp_name))
    for name in (log_name, ".rlexp.lock"):
        if name:
            check_appendable(run_dir / name)


@dataclass
class PlannedDir:
    """Where a command line will write: the run dir, or the sweep dir (its jobs' dirs below)."""

    path: Path
    key: str  # the config key that sets it: hydra.run.dir or hydra.sweep.dir
    exp_name: str
    log_name: str  # the job's log file Hydra opens in a run dir

    @property
    def sweep(self) -> bool:
        return self.key == "hydra.sweep.dir"


def planned_dir(cfg: Any, multirun: bool) -> PlannedDir | None:
    """The run or sweep dir of a composed config with its ``hydra`` node (None where it cannot be
    resolved before Hydra runs, e.g. an interpolation of the job's own runtime values)."""
    from omegaconf import OmegaConf

    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    try:
        path = OmegaConf.select(cfg, key, throw_on_resolution_failure=True)
        exp_name = str(OmegaConf.select(cfg, "trainer.exp_name", default="rlexp"))
        job = OmegaConf.select(cfg, "hydra.job.name", default="train")
    except Exception:
        return None
    if path is None:
        return None
    return PlannedDir(Path(str(path)), key, exp_name, f"{job}.log")


#: Job dirs of an earlier attempt checked in a sweep dir (a re-run writes into each of them).
MAX_JOB_DIRS = 10_000


def _job_dirs(sweep_dir: Path) -> list[Path]:
    """The dirs in ``sweep_dir`` that an earlier attempt of a sweep ran a job in."""
    try:
        entries = sorted(os.scandir(sweep_dir), key=lambda e: e.name)[:MAX_JOB_DIRS]
    except OSError:
        return []
    return [
        Path(e.path)
        for e in entries
        if e.is_dir(follow_symlinks=False) and os.path.lexists(os.path.join(e.path, ".rlexp.lock"))
    ]


def check_planned_dir(planned: PlannedDir | None) -> None:
    """``ConfigError`` (one line: the dir, the path that failed, why, the key to change) when the
    run or sweep dir, or a job dir a sweep re-runs in, cannot be created or written at the longest
    path its runs write."""
    if planned is None:
        return
    from rlexp.config.validate import ConfigError

    longest = run_dir_longest(planned.exp_name)
    dirs = [planned.path]
    try:
        if planned.sweep:
            probe_dir(planned.path, longest + len("0/"))
            dirs = _job_dirs(planned.path)
        for run_dir in dirs:
            check_run_dir_writable(run_dir, planned.exp_name, planned.log_name)
    except OSError as exc:
        what = f"{planned.key} {'(the sweep dir)' if planned.sweep else '(the run dir)'}"
        fix = f"use another {planned.key}, or make it writable"
        raise ConfigError(describe(exc, what, planned.path, longest, fix)) from None


def check_checkpoints_writable(ckpt_dir: Path, exp_name: str) -> None:
    """``OSError`` unless a checkpoint can be written in ``ckpt_dir`` (created, and kept) under the
    longest temporary name it will have: checked before training, not at the first save."""
    probe_dir(ckpt_dir, len(checkpoint_temp_name(exp_name)), keep=True)
