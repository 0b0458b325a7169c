"""A PBT population on a shared filesystem: what each member publishes in ``<run_dir>/pbt/`` at a
ready point, how its siblings read it, and the exploit/explore decisions (pure functions).

A member at a ready point hard-links the checkpoint it just wrote to ``pbt/ready_step_N.pt`` (a
new name, made by one rename: a reader sees the whole file or none) and appends one line to
``pbt/ready.jsonl`` (step, generation, score, hyperparameters, that file's name). The members are
the sweep's own jobs 0 .. ``population_size - 1``, each known by its dir (named by the sweep's
``hydra.sweep.subdir`` in its ``multirun.yaml``), never by what a file inside says; any other dir in
the sweep dir (an earlier sweep's job, a copied or symlinked run) is a stray: ignored, and named. A member that exploits links the source's ready file
into its own ``pbt/incoming.pt`` before reading it: from then on no pruning on the source's side
(its ``checkpoints/`` keep_last, or its own ``keep_ready``) can take the bytes away. A sibling's
files are another job's: read bounded (``rlexp.files.safe_read``), never trusted.
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

from rlexp.files import safe_read
from rlexp.files.fsutil import atomic_write
from rlexp.pbt.config import PBTConfig, log_uniform

log = logging.getLogger(__name__)

PBT_DIR = "pbt"
READY_LOG = "ready.jsonl"
LINEAGE = "lineage.jsonl"
INCOMING = "incoming.pt"
#: Bytes of a sibling's ready.jsonl read at most (a line is ~300 bytes: thousands of ready points).
READY_READ = 4 << 20
#: How Hydra names a job dir after its number (conf/config.yaml's ``hydra.sweep.subdir``).
JOB_NUM = "${hydra.job.num}"
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


#: The fields of a ``ready.jsonl`` line, type- and range-checked (``safe_read``).
READY_FIELDS: dict[str, safe_read.Check] = {
    "step": safe_read.whole(),
    "generation": safe_read.whole(),
    "score": safe_read.number(),
    "checkpoint": safe_read.text(64),
    "hyperparameters": lambda v: hyperparameter_values(v),
    "time": safe_read.number(0, 1e11),
}
#: A hyperparameter's name (a schema field's): nothing that could be a YAML key or path.
_NAME = r"[a-z][a-z0-9_]{0,63}"


def hyperparameter_values(v: Any) -> str:
    """A ``safe_read`` check: an object of hyperparameter name -> finite number."""
    if not isinstance(v, dict):
        return "is not an object"
    for name, value in v.items():
        why = safe_read.text(64, _NAME)(name) or safe_read.number()(value)
        if why:
            return f"holds {safe_read.shown(name)}: {safe_read.shown(value)}, which {why}"
    return ""


def read_ready(member_dir: Path, problems: list[str] | None = None) -> list[Ready]:
    """A member's ready points, oldest first; [] for a dir without any (or unreadable). The member
    is the dir's name, whatever a line says; a line that fails its checks (type, range, a snapshot
    name that is not its step's) is left out and named in ``problems``."""
    try:
        data = safe_read.read_bytes(member_dir / PBT_DIR / READY_LOG, READY_READ)
    except safe_read.Unreadable as exc:
        if problems is not None:
            problems.append(f"{PBT_DIR}/{READY_LOG}: {exc}")
        return []
    if not data:
        return []
    out = []
    for i, line in enumerate(data[: data.rfind(b"\n") + 1].splitlines(), 1):  # complete lines
        try:
            row = safe_read.check_fields(safe_read.parse_json(line), READY_FIELDS)
            step = row.get("step")
            if not isinstance(step, int) or row.get("checkpoint") != ready_name(step):
                raise safe_read.Unreadable(
                    f"checkpoint {safe_read.shown(row.get('checkpoint'))} is not the snapshot "
                    f"of its step {safe_read.shown(row.get('step'))}"
                )
            if row.get("generation") is None or row.get("hyperparameters") is None:
                raise safe_read.Unreadable("generation or hyperparameters missing")
            score = row.get("score")
            out.append(
                Ready(
                    member=member_dir.name,
                    step=row["step"],
                    generation=row["generation"],
                    score=None if score is None else float(score),
                    checkpoint=row["checkpoint"],
                    hyperparameters={k: float(v) for k, v in row["hyperparameters"].items()},
                    time=float(row.get("time") or 0.0),
                )
            )
        except safe_read.Unreadable as exc:
            if problems is not None:
                problems.append(f"{PBT_DIR}/{READY_LOG} line {i}: {exc}")
    return out


def job_names(sweep_dir: Path, size: int) -> list[str]:
    """The dir names of the sweep's jobs 0 .. ``size - 1``: ``hydra.sweep.subdir`` of its
    ``multirun.yaml`` with the job number in (``${hydra.job.num}`` when it cannot be read: the
    config's default; ``rlexp.pbt.config.check_pbt_subdir`` refuses any other form up front)."""
    template = JOB_NUM
    try:
        data = safe_read.load_yaml(sweep_dir / "multirun.yaml")
        sub = data["hydra"]["sweep"]["subdir"]
        if isinstance(sub, (str, int)) and not isinstance(sub, bool):
            template = str(sub)
    except (safe_read.Unreadable, KeyError, TypeError):
        pass
    if template.count(JOB_NUM) != 1 or "/" in template:
        template = JOB_NUM
    return [template.replace(JOB_NUM, str(i)) for i in range(size)]


def scan(sweep_dir: Path, names: list[str]) -> tuple[dict[str, Path], dict[str, str]]:
    """(the member dirs there are, by name: real dirs only; the strays: every other dir or
    symlink of the sweep dir, with why it is not a member)."""
    wanted = set(names)
    members: dict[str, Path] = {}
    strays: dict[str, str] = {}
    try:
        entries = sorted(os.scandir(sweep_dir), key=lambda e: e.name)
    except OSError:
        return members, strays
    for entry in entries:
        if entry.name.startswith("."):
            continue
        try:
            link, is_dir = entry.is_symlink(), entry.is_dir()  # is_dir follows the link
        except OSError:
            continue
        if link and is_dir:
            strays[entry.name] = "a symlink, not a job's own dir"
        elif is_dir and entry.name in wanted:
            members[entry.name] = Path(entry.path)
        elif is_dir:
            strays[entry.name] = "not one of the sweep's jobs"
    return members, strays


def name_strays(strays: dict[str, str], named: set[str]) -> None:
    """One warning naming the strays not named before (``named`` is updated)."""
    new = {name: why for name, why in strays.items() if name not in named}
    if new:
        named.update(new)
        log.warning(
            "[pbt] ignored in the sweep dir (not members of this population, never sources): %s",
            "; ".join(f"{name} ({why})" for name, why in new.items()),
        )


def siblings(run_dir: Path, names: list[str]) -> list[Path]:
    """The other members' dirs (those there are), by name."""
    members, _ = scan(run_dir.parent, names)
    return [p for name, p in members.items() if name != run_dir.name]


def population(
    run_dir: Path, names: list[str], generation: int | None, problems: list[str] | None = None
) -> dict[str, tuple[Path, Ready]]:
    """Each sibling's ready point of ``generation`` (None: its newest), by member name."""
    found: dict[str, tuple[Path, Ready]] = {}
    for sib in siblings(run_dir, names):
        recs = read_ready(sib, problems)
        if generation is not None:
            recs = [r for r in recs if r.generation == generation]
        if recs:
            found[sib.name] = (sib, recs[-1])
    return found


def wait_for_generation(
    run_dir: Path, names: list[str], generation: int, timeout_s: float, poll_s: float = 0.2
) -> tuple[dict[str, tuple[Path, Ready]], list[str]]:
    """Sync mode: the siblings' ready points of ``generation``, waiting until every other member
    of ``names`` has reached it (or passed it) or ``timeout_s`` has passed; (population, the
    dropped members: those seen behind, and one 'never seen' per member that has no dir or record
    yet)."""
    deadline = time.monotonic() + timeout_s
    size = len(names)
    while True:
        reached = {}
        behind, ended = [], []
        for sib in siblings(run_dir, names):
            recs = read_ready(sib)
            if recs and recs[-1].generation >= generation:
                at = [r for r in recs if r.generation == generation]
                if at:
                    reached[sib.name] = (sib, at[-1])
                    continue
            state = ended_state(sib)
            if state is not None:  # failed, killed, stopped early: it will not reach this point
                ended.append(f"{sib.name} ({state})")
            elif recs:
                behind.append(f"{sib.name} (at step {recs[-1].step})")
        if len(reached) + len(ended) >= size - 1 or time.monotonic() >= deadline:
            break
        time.sleep(poll_s)
    if len(reached) >= size - 1:
        return reached, []
    unseen = max(0, size - 1 - len(reached) - len(behind) - len(ended))
    return reached, ended + behind + ["a member never seen"] * unseen


#: A member's status.json states that say it will not reach another ready point (rlexp.run.lifecycle
#: writes them; the local launcher's job pool writes ``failed`` for a job that died): not waited for
#: in sync mode. ``interrupted`` is not one: a stopped or preempted member may be resumed (SLURM
#: requeues it) and is waited for up to ``sync_timeout_s`` like a running one.
ENDED_STATES = ("failed", "stopped_early", "pruned", "finished")


def ended_state(member_dir: Path) -> str | None:
    """The member's ended state (one of ENDED_STATES), or None: running, not started, unreadable."""
    try:
        state = safe_read.read_checked(member_dir / "status.json", safe_read.STATUS_FIELDS).get(
            "state"
        )
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return state if state in ENDED_STATES else None


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


#: The fields of a lineage record, by event (``safe_read`` checks; the starred ones required).
_EXPLORE = r"x[0-9.e+-]{1,24}|resampled"
LINEAGE_FIELDS: dict[str, dict[str, safe_read.Check]] = {
    "start": {"*step": safe_read.whole(), "member": safe_read.text(),
              "*hyperparameters": hyperparameter_values},
    "exploit": {"*step": safe_read.whole(), "*generation": safe_read.whole(),
                "member": safe_read.text(), "*score": safe_read.number(),
                "*source": safe_read.text(), "*source_step": safe_read.whole(),
                "*source_score": safe_read.number(), "old": hyperparameter_values,
                "copied": hyperparameter_values, "*new": hyperparameter_values,
                "explore": lambda v: _explore_marks(v)},
}  # fmt: skip


def _explore_marks(v: Any) -> str:
    if not isinstance(v, dict):
        return "is not an object"
    bad = next((k for k, x in v.items() if safe_read.text(32, _EXPLORE)(x)), None)
    return "" if bad is None else f"holds {safe_read.shown(bad)}: {safe_read.shown(v[bad])}"


def check_lineage_row(row: Any, last_step: int) -> dict[str, Any]:
    """One lineage record, checked: its event's fields typed and in range, every hyperparameter
    value one its config field accepts, its step not before the one above it; Unreadable why."""
    if not isinstance(row, dict) or row.get("event") not in LINEAGE_FIELDS:
        raise safe_read.Unreadable("not a start or exploit record")
    fields = LINEAGE_FIELDS[row["event"]]
    safe_read.check_fields(row, {k.lstrip("*"): check for k, check in fields.items()})
    missing = [k[1:] for k in fields if k.startswith("*") and row.get(k[1:]) is None]
    if missing:
        raise safe_read.Unreadable(f"a {row['event']} record without {missing[0]}")
    if row["step"] < last_step:
        raise safe_read.Unreadable(f"step {row['step']} comes after step {last_step}")
    values = row["hyperparameters"] if row["event"] == "start" else row["new"]
    for name, value in values.items():
        why = out_of_range(name, value)
        if why:
            raise safe_read.Unreadable(why)
    return row


def out_of_range(name: str, value: float) -> str:
    """ "" when ``value`` is one ``algorithm.<name>`` may hold (``rlexp.config.rules``), else why."""
    from rlexp.config.rules import FIELD_RULES

    rule = FIELD_RULES.get(f"algorithm.{name}")
    if rule is None or rule.check(value):
        return ""
    return f"{name}={safe_read.shown(value)} is out of range (algorithm.{name} must be {rule.text})"


def read_lineage(run_dir: Path) -> list[dict[str, Any]]:
    """A member's lineage records (``pbt/lineage.jsonl``), bounded and checked (``check_lineage_row``);
    [] when there is none; Unreadable (naming the line and the value) when one record fails."""
    data = safe_read.read_bytes(run_dir / PBT_DIR / LINEAGE, READY_READ)
    rows: list[dict[str, Any]] = []
    for i, line in enumerate((data or b"").splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = check_lineage_row(safe_read.parse_json(line), rows[-1]["step"] if rows else 0)
        except safe_read.Unreadable as exc:
            raise safe_read.Unreadable(f"line {i}: {exc}") from None
        rows.append(row)
    return rows
