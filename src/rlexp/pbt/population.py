"""A PBT population on a shared filesystem: what each member publishes in ``<run_dir>/pbt/`` at a
ready point, how its siblings read it, and the exploit/explore decisions (pure functions).

A member at a ready point hard-links the checkpoint it just wrote to ``pbt/ready_step_N.pt`` (a
new name, made by one rename: a reader sees the whole file or none) and appends one line to
``pbt/ready.jsonl`` (step, generation, score, hyperparameters, that file's name). Sibling run
dirs are the other dirs of the sweep dir. A member that exploits links the source's ready file
into its own ``pbt/incoming.pt`` before reading it: from then on no pruning on the source's side
(its ``checkpoints/`` keep_last, or its own ``keep_ready``) can take the bytes away. A sibling's
files are another job's: read bounded (``rlexp.safe_read``), never trusted.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rlexp import safe_read
from rlexp.fsutil import atomic_write
from rlexp.pbt.config import PBTConfig, log_uniform

log = logging.getLogger(__name__)

PBT_DIR = "pbt"
READY_LOG = "ready.jsonl"
LINEAGE = "lineage.jsonl"
INCOMING = "incoming.pt"
#: Bytes of a sibling's ready.jsonl read at most (a line is ~300 bytes: thousands of ready points).
READY_READ = 4 << 20
_READY_RE = re.compile(r"^ready_step_(\d{9,})\.pt$")


@dataclass(frozen=True)
class Ready:
    """One member at one ready point: what siblings rank and copy."""

    member: str
    step: int
    generation: int
    score: float | None  # None: no episode finished yet (never a source)
    checkpoint: str  # file name in the member's pbt/
    hyperparameters: dict[str, float]
    time: float = 0.0

    def line(self) -> str:
        return json.dumps(asdict(self), allow_nan=False) + "\n"


def ready_name(step: int) -> str:
    return f"ready_step_{step:09d}.pt"


def publish(run_dir: Path, checkpoint: Path, rec: Ready, keep: int) -> None:
    """Make ``checkpoint`` this member's ready snapshot at ``rec.step`` and announce it; keep the
    newest ``keep`` snapshots (a sibling that took one holds its own link)."""
    pdir = run_dir / PBT_DIR
    pdir.mkdir(parents=True, exist_ok=True)
    dest = pdir / rec.checkpoint
    link(checkpoint, dest)
    with open(pdir / READY_LOG, "a", encoding="utf-8") as f:  # one short line: one write
        f.write(rec.line())
        f.flush()
        os.fsync(f.fileno())
    snapshots = sorted(p for p in pdir.iterdir() if _READY_RE.match(p.name))
    for old in snapshots[:-keep]:
        old.unlink(missing_ok=True)


def link(src: Path, dest: Path) -> None:
    """``dest`` becomes ``src``'s bytes in one rename: a hard link (no copy, and the bytes live as
    long as either name does), or a copy where the filesystem has no hard links."""

    def write(tmp: Path) -> None:  # atomic_write's temporary file, replaced by the link
        tmp.unlink()
        try:
            os.link(src, tmp)
        except FileNotFoundError:
            raise
        except OSError:  # EXDEV, EPERM (some network filesystems): copy the open file
            with open(src, "rb") as fin, open(tmp, "wb") as fout:
                shutil.copyfileobj(fin, fout)

    atomic_write(dest, write, fsync=False)  # the checkpoint's bytes were synced when it was saved


def read_ready(member_dir: Path) -> list[Ready]:
    """A member's ready points, oldest first; [] for a dir without any (or unreadable)."""
    try:
        data = safe_read.read_bytes(member_dir / PBT_DIR / READY_LOG, READY_READ)
    except safe_read.Unreadable as exc:
        log.warning("[pbt] %s: %s; left out of the population", member_dir, exc)
        return []
    if not data:
        return []
    out = []
    for line in data[: data.rfind(b"\n") + 1].splitlines():  # complete lines only
        try:
            row = safe_read.parse_json(line)
            score = row["score"]
            out.append(
                Ready(
                    member=str(row["member"])[:256],
                    step=int(row["step"]),
                    generation=int(row["generation"]),
                    score=None
                    if score is None or not math.isfinite(float(score))
                    else float(score),
                    checkpoint=str(row["checkpoint"]),
                    hyperparameters={str(k): float(v) for k, v in row["hyperparameters"].items()},
                    time=float(row.get("time", 0.0)),
                )
            )
        except (ValueError, KeyError, TypeError, AttributeError, OverflowError):
            continue
    return [r for r in out if _READY_RE.match(r.checkpoint)]


def siblings(run_dir: Path) -> list[Path]:
    """The other job dirs of the sweep dir (this run dir's parent), by name."""
    try:
        entries = sorted(run_dir.parent.iterdir())
    except OSError:
        return []
    return [p for p in entries if p != run_dir and p.is_dir() and not p.name.startswith(".")]


def population(run_dir: Path, generation: int | None) -> dict[str, tuple[Path, Ready]]:
    """Each sibling's ready point of ``generation`` (None: its newest), by member name."""
    found: dict[str, tuple[Path, Ready]] = {}
    for sib in siblings(run_dir):
        recs = read_ready(sib)
        if generation is not None:
            recs = [r for r in recs if r.generation == generation]
        if recs:
            found[sib.name] = (sib, recs[-1])
    return found


def wait_for_generation(
    run_dir: Path, generation: int, size: int, timeout_s: float, poll_s: float = 0.2
) -> tuple[dict[str, tuple[Path, Ready]], list[str]]:
    """Sync mode: the siblings' ready points of ``generation``, waiting until ``size - 1`` siblings
    have reached it (or passed it) or ``timeout_s`` has passed; (population, the dropped members:
    those seen behind, and one 'never seen' per member that has no dir or record yet)."""
    deadline = time.monotonic() + timeout_s
    while True:
        reached = {}
        behind = []
        for sib in siblings(run_dir):
            recs = read_ready(sib)
            if recs and recs[-1].generation >= generation:
                at = [r for r in recs if r.generation == generation]
                if at:
                    reached[sib.name] = (sib, at[-1])
            elif recs:
                behind.append(f"{sib.name} (at step {recs[-1].step})")
        if len(reached) >= size - 1 or time.monotonic() >= deadline:
            break
        time.sleep(poll_s)
    if len(reached) >= size - 1:
        return reached, []
    unseen = max(0, size - 1 - len(reached) - len(behind))
    return reached, behind + ["a member never seen"] * unseen


def quantiles(ranked: list[str], quantile: float) -> tuple[list[str], list[str]]:
    """(bottom, top) members of ``ranked`` (worst first): ceil(n * quantile) each, at most n // 2
    (Ray's rule): two members make one bottom and one top, one member none."""
    n = len(ranked)
    k = min(int(math.ceil(n * quantile)), n // 2)
    return ranked[:k], ranked[n - k :] if k else []


def decision_rng(seed: int, member: str, generation: int) -> np.random.Generator:
    """The draws of one member at one ready point: the same seeds give the same decisions,
    whatever order the members reach the point in."""
    return np.random.default_rng([seed, zlib.crc32(member.encode()), generation])


def choose_source(
    me: Ready, others: dict[str, tuple[Path, Ready]], cfg: PBTConfig, rng: np.random.Generator
) -> tuple[Path, Ready] | None:
    """The member to copy when ``me`` is in the bottom quantile: one drawn from the top quantile
    among those with a score and a snapshot, only if it beats ``me`` (a population where none does
    copies nothing, never the worst)."""
    if me.score is None:
        return None
    scored = {name: pr for name, pr in others.items() if pr[1].score is not None}
    scores = {me.member: me.score, **{name: pr[1].score for name, pr in scored.items()}}
    ranked = sorted(scores, key=lambda name: (scores[name], name))
    bottom, top = quantiles(ranked, cfg.quantile)
    if me.member not in bottom:
        return None
    better = [name for name in top if scores[name] > me.score + cfg.min_improvement]
    if not better:
        return None
    return scored[better[int(rng.integers(len(better)))]]


def explore(
    values: dict[str, float], cfg: PBTConfig, rng: np.random.Generator
) -> tuple[dict[str, float], dict[str, str]]:
    """Perturb or resample each hyperparameter PBT tunes (the others are left as they are): new
    values, and how each one came (``x1.2``, ``resampled``), always within the bounds."""
    new, how = dict(values), {}
    for name, r in cfg.hyperparameters.items():
        if rng.random() < cfg.resample_probability:
            value = log_uniform(rng, r.low, r.high) if r.log else float(rng.uniform(r.low, r.high))
            how[name] = "resampled"
        else:
            factor = float(cfg.perturb_factors[int(rng.integers(len(cfg.perturb_factors)))])
            value = values[name] * factor
            how[name] = f"x{factor:g}"
        new[name] = min(r.high, max(r.low, value))
    return new, how


def initial(values: dict[str, float], cfg: PBTConfig, rng: np.random.Generator) -> dict[str, float]:
    """A member's starting hyperparameters: the config's, or (``init: sample``) drawn in bounds."""
    if cfg.init == "config":
        return {name: values[name] for name in cfg.hyperparameters}
    return {
        name: log_uniform(rng, r.low, r.high) if r.log else float(rng.uniform(r.low, r.high))
        for name, r in cfg.hyperparameters.items()
    }


def take(source_dir: Path, rec: Ready, dest: Path) -> bool:
    """Link the source's ready snapshot to ``dest`` (ours from now on, whatever the source prunes);
    False when the source has pruned it meanwhile (it moved on two ready points)."""
    try:
        link(source_dir / PBT_DIR / rec.checkpoint, dest)
    except FileNotFoundError:
        return False
    return True


def read_lineage(run_dir: Path) -> list[dict[str, Any]]:
    """A member's lineage records (``pbt/lineage.jsonl``), bounded; [] when there are none."""
    try:
        data = safe_read.read_bytes(run_dir / PBT_DIR / LINEAGE, READY_READ)
    except safe_read.Unreadable:
        return []
    rows = []
    for line in (data or b"").splitlines():
        try:
            row = safe_read.parse_json(line)
        except ValueError:
            continue
        if isinstance(row, dict) and isinstance(row.get("step"), int):
            rows.append(row)
    return rows
