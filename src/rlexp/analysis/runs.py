"""``rlexp runs [DIR ...]``: every run dir under ``outputs/`` and ``multirun/`` as one table row.

A run dir is a dir holding ``status.json``, ``config.yaml`` or ``.hydra/``. Only small files are
read (``status.json``, ``heartbeat.json``, ``provenance.json``, ``config.yaml``,
``.hydra/overrides.yaml``; for a best eval the heartbeat has no answer to, at most the last
TAIL_BYTES of ``metrics.jsonl``), so thousands of runs list in about a second. A run whose
``status.json`` says ``running`` is checked against its heartbeat and its PID (``rlexp.analysis.liveness``);
the rules are in docs/runs.md. Every file is read through ``rlexp.files.safe_read`` (bounded, checked):
what a damaged run dir holds is left out, and said in one warning line naming the dir (a bad
``status.json``: the run shows ``unknown``). Symlinked run dirs and date dirs are followed, each
run listed once (``rlexp.files.dirwalk``).
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, NamedTuple

import yaml

from rlexp.analysis.liveness import Here, liveness, parse_time
from rlexp.analysis.reporting.jobs import DEFAULT_METRIC, json_number
from rlexp.analysis.run_files import flatten, read_checked, read_config, read_overrides  # noqa: F401
from rlexp.common.table import format_count, format_duration, format_number, print_table
from rlexp.files import safe_read
from rlexp.files.dirwalk import find_dirs

#: Searched when no dir is given, under the working dir.
DEFAULT_DIRS = ("outputs", "multirun")
#: Any of these in a dir makes it a run dir (one with none was never started by rlexp).
MARKERS = ("status.json", "config.yaml", ".hydra")
#: Dirs inside a run dir that never hold another run.
SKIP_DIRS = frozenset({"tensorboard", "checkpoints", "wandb", "__pycache__"})
#: At most this much of the end of ``metrics.jsonl`` is read for a best eval (a run from before
#: ``heartbeat.json``, or a metric other than ``trainer.best_metric``).
TAIL_BYTES = 256 * 1024
#: What the status column shows: status.json's states, and died | stalled | running? | unknown.
STATES = tuple(
    "running finished stopped_early pruned interrupted stopped failed died stalled running? unknown".split()
)
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
log = logging.getLogger(__name__)


class RunsError(ValueError):
    """Bad input to ``rlexp runs`` / ``rlexp compare``: one line naming the path or the key."""


@dataclass
class Run:
    """What one run dir says about its run."""

    path: Path
    status: str  # status.json's state, or died | stalled | running? | unknown (docs/runs.md)
    note: str = ""  # why a run shows died / stalled / running?, or what could not be read
    task: str | None = None
    algorithm: str | None = None
    step: int | None = None
    total: int | None = None
    last: float | None = None
    best: float | None = None
    best_exact: bool = True  # False: the best over the tail of metrics.jsonl only (a lower bound)
    wall_s: float | None = None
    start: str | None = None
    host: str | None = None
    git: str | None = None
    overrides: list[str] = field(default_factory=list)
    resume: str | None = None  # the command that continues a died run
    hyperparameters: dict[str, float] = field(default_factory=dict)  # a PBT member's current ones
    problems: list[str] = field(default_factory=list)  # files left out: "name: why" (warn_problems)

    @cached_property
    def config(self) -> dict[str, Any]:
        """The flattened ``config.yaml``, read on first use (YAML costs ~0.5 ms a run)."""
        return read_config(self.path, self.problems)

    def to_json(self) -> dict[str, Any]:
        """The run as a JSON object for ``--json`` (the config is left out)."""
        out = {k: v for k, v in vars(self).items() if k != "config"}
        out["path"] = str(self.path)
        return out


# -- finding and reading run dirs ------------------------------------------------------------------
def find_run_dirs(roots: list[Path]) -> list[Path]:
    """Every run dir at or under ``roots`` (a run dir's own subdirs are not searched)."""
    for root in roots:
        if not root.is_dir():
            raise RunsError(f"{root}: no such dir")
    found = find_dirs(
        roots,
        wanted=lambda _, names: not names.isdisjoint(MARKERS),
        skip=lambda name: name.startswith(".") or name in SKIP_DIRS,
    )
    return sorted(found)


_NUMBER = rb"(-?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)"
_STEP = re.compile(rb'"step": (\d+)')
_MAX_DIGITS = len(str(safe_read.MAX_INT))
_CKPT_STEP = re.compile(
    r"_step_(\d+)\.pt$"
)  # rlexp.checkpoints.files's names (not imported: torch)


class Tail(NamedTuple):
    """What the end of ``metrics.jsonl`` says: the metric's last and best value, whether that is
    the whole file, and the last logged step."""

    last: float | None
    best: float | None
    exact: bool
    step: int | None


def tail_metric(path: Path, metric: str, problems: list[str] | None = None) -> Tail:
    """``Tail`` of ``metric`` over at most the last TAIL_BYTES of ``metrics.jsonl``, without
    parsing its JSON; non-finite values and steps out of range are left out (and named)."""
    try:
        data, size = safe_read.read_tail(path, TAIL_BYTES) or (b"", 0)
    except safe_read.Unreadable as exc:
        if problems is not None:
            problems.append(f"{path.name}: {exc}")
        return Tail(None, None, True, None)
    pattern = re.compile(b'"' + re.escape(metric.encode()) + b'": ' + _NUMBER)
    values = [v for v in map(float, pattern.findall(data)) if abs(v) < float("inf")]
    steps = _STEP.findall(data)
    step = int(steps[-1]) if steps and len(steps[-1]) <= _MAX_DIGITS else None
    if step is None or step > safe_read.MAX_INT:
        if steps and problems is not None:
            problems.append(
                f"{path.name}: step {safe_read.shown(steps[-1].decode())} is out of range"
            )
        step = None
    if not values:
        return Tail(None, None, size <= TAIL_BYTES, step)
    return Tail(values[-1], max(values), size <= TAIL_BYTES, step)


def newest_checkpoint_step(run_dir: Path) -> int | None:
    """The step of the newest ``*_step_N.pt`` in ``checkpoints/`` (what a resume continues from
    if that file is good), from the names alone."""
    try:
        names = os.listdir(run_dir / "checkpoints")
    except OSError:
        return None
    steps = [int(m.group(1)) for n in names if (m := _CKPT_STEP.search(n))]
    return max(steps, default=None)


# -- one run ---------------------------------------------------------------------------------------
def resume_command(run_dir: Path, overrides: list[str], argv: Any) -> str:
    """The command that resumes a run from before ``provenance.json`` recorded ``launch``
    (``rlexp.runtime.relaunch.legacy_resume_command``)."""
    from rlexp.runtime.relaunch import legacy_resume_command

    return legacy_resume_command(run_dir, overrides, argv)


def _budget(config: dict[str, Any]) -> int | None:
    """The env steps a run was to train, from its config; None when it does not say in range."""
    iterations, batch = config.get("trainer.iterations"), config.get("trainer.frames_per_batch")
    if _int(iterations) is not None and _int(batch) is not None:
        return _int(iterations * batch)
    return _int(config.get("trainer.total_frames"))


def _int(*values: Any) -> int | None:
    """The largest of ``values`` that is a step (a whole number in [0, MAX_INT])."""
    ints = [v for v in values if not safe_read.whole()(v)]
    return max(ints) if ints else None


def _name(value: Any) -> str | None:
    """A config's name (``env.name``): a string, else None."""
    return value if isinstance(value, str) else None


def _evals(run: Run, status: dict, beat: dict, metric: str) -> None:
    """Last and best eval: status.json's final eval, the heartbeat's, else the metrics tail."""
    final = status.get("final_eval") if run.status != "running" else None
    last = json_number((final or {}).get(metric)) if isinstance(final, dict) else None
    if last is None and isinstance(beat.get("last_eval"), dict):
        last = json_number(beat["last_eval"].get(metric))
    best = json_number(beat.get("best")) if beat.get("best_metric") == metric else None
    if best is None or last is None or status.get("state") == "running":
        tail = tail_metric(run.path / "metrics.jsonl", metric, run.problems)
        last = last if last is not None else tail.last
        if best is None:
            best, run.best_exact = tail.best, tail.exact
        run.step = _int(run.step, tail.step)  # newer than a heartbeat up to 10 s old
    if last is not None:
        best = last if best is None else max(best, last)
    run.last, run.best = last, best


def _wall(run: Run, status: dict, beat: dict, start: float | None, now: float) -> None:
    if run.status == "running":
        end: float | None = now
    elif run.status in ("died", "stalled"):
        times = [json_number(beat.get("time"))]
        try:
            times.append((run.path / "metrics.jsonl").stat().st_mtime)
        except OSError:
            pass
        end = max((t for t in times if t is not None), default=None)
    else:
        end = parse_time(status.get("time"))
    if start is not None and end is not None and end >= start:
        run.wall_s = end - start


def read_run(
    run_dir: Path, metric: str = DEFAULT_METRIC, here: Here | None = None, now: float | None = None
) -> Run:
    """One run dir's row (``here``/``now``: this host and time, for the liveness rules)."""
    here, now = here or Here.now(), time.time() if now is None else now
    problems: list[str] = []
    status = read_checked(run_dir, "status.json", problems, safe_read.STATUS_FIELDS)
    beat = read_checked(run_dir, "heartbeat.json", problems, safe_read.HEARTBEAT_FIELDS)
    prov = read_checked(run_dir, "provenance.json", problems, safe_read.PROVENANCE_FIELDS)
    shown, note = liveness(status, beat, now, here)
    if problems and problems[0].startswith("status.json"):
        note = problems[0]
    project = prov.get("project") if isinstance(prov.get("project"), dict) else {}
    commit = project.get("git_commit") or prov.get("git_commit")
    dirty = project.get("git_dirty") if project.get("git_commit") else prov.get("git_dirty")
    run = Run(
        path=run_dir,
        status=shown,
        note=note,
        step=_int(status.get("global_step"), beat.get("global_step")),
        start=prov.get("start_time"),
        host=prov.get("host") or status.get("host") or beat.get("host"),
        git=(str(commit)[:8] + ("+dirty" if dirty else "")) if commit else None,
        overrides=read_overrides(run_dir, problems),
        problems=problems,
    )
    # The heartbeat names task, algorithm and budget; older runs: their config.yaml.
    run.task = beat.get("task") or _name(run.config.get("env.name"))
    run.algorithm = beat.get("algorithm") or _name(run.config.get("algorithm.name"))
    run.total = _int(beat.get("total")) or _budget(run.config)
    _evals(run, status, beat, metric)
    if (run_dir / "pbt" / "lineage.jsonl").is_file():  # a PBT member: what its lineage last set
        from rlexp.pbt.lineage import read_member

        try:
            member = read_member(run_dir, metric)
            run.hyperparameters = member.current()
            problems += member.problems
        except safe_read.Unreadable as exc:  # one bad value: this run's hyperparameters left out
            problems.append(str(exc))
    _wall(run, status, beat, parse_time(run.start), now)
    if shown == "died":
        from rlexp.runtime.relaunch import resume_command as command  # cwd, entry, ranks, quoting

        run.resume = command(run_dir.resolve(), run.overrides, prov)
        ckpt = newest_checkpoint_step(run_dir)
        run.note += f"; resumes from step {ckpt}" if ckpt is not None else "; no checkpoint yet"
    return run


def read_runs(roots: list[Path], metric: str = DEFAULT_METRIC) -> list[Run]:
    """Every run under ``roots``, read once with one view of this host and time."""
    here, now = Here.now(), time.time()
    return [read_run(d, metric, here, now) for d in find_run_dirs(roots)]


def warn_problems(runs: list[Run], command: str) -> None:
    """One warning line per run that had files left out: its dir and why."""
    for r in runs:
        if r.problems:
            log.warning("rlexp %s: %s: %s", command, r.path, "; ".join(dict.fromkeys(r.problems)))


# -- the table: columns, filters, sorting ----------------------------------------------------------
def _rel(path: Path) -> str:
    """The path as found (a symlinked run dir under its link's name), relative to the cwd."""
    for here, cwd in (
        (Path(os.path.abspath(path)), Path.cwd()),
        (path.resolve(), Path.cwd().resolve()),
    ):
        try:
            return str(here.relative_to(cwd))
        except ValueError:
            continue
    return str(path)


#: The table's columns (``--sort`` takes these, ``total``, ``progress``, or any config key).
COLUMNS = tuple("dir status task algo steps last best wall start host git overrides".split())
NUMERIC = ("steps", "last", "best", "wall")


def cells(r: Run) -> list[str]:
    """One table row, in COLUMNS order."""
    best = ("" if r.best_exact or r.best is None else ">=") + format_number(r.best)
    return [
        _rel(r.path),
        r.status,
        r.task or "-",
        r.algorithm or "-",
        f"{format_count(r.step)}/{format_count(r.total)}",
        format_number(r.last),
        best,
        "-" if r.wall_s is None else format_duration(r.wall_s),
        (r.start or "-")[:16].replace("T", " "),
        r.host or "-",
        r.git or "-",
        " ".join(r.overrides),
    ]


def _value(r: Run, key: str) -> Any:
    """What ``--sort`` / ``--where`` compare for ``key``: a column's value or the config's."""
    values = {
        "dir": str(r.path),
        "status": r.status,
        "task": r.task,
        "algo": r.algorithm,
        "steps": r.step,
        "total": r.total,
        "last": r.last,
        "best": r.best,
        "wall": r.wall_s,
        "start": parse_time(r.start),
        "host": r.host,
        "git": r.git,
        "overrides": " ".join(r.overrides),
        "progress": r.step / r.total if r.step is not None and r.total else None,
    }
    values |= {"env.name": r.task, "algorithm.name": r.algorithm}  # no config.yaml to read
    return values[key] if key in values else r.config.get(key)


def _close(key: str, choices: list[str]) -> str:
    import difflib

    near = difflib.get_close_matches(key, choices, n=1)
    return f"; did you mean {near[0]!r}?" if near else ""


def check_key(key: str, runs: list[Run], what: str) -> None:
    columns = (*COLUMNS, "total", "progress")
    if key in columns or any(key in r.config for r in runs) or not runs:
        return
    known = sorted({*columns, *(k for r in runs for k in r.config)})
    raise RunsError(
        f"{what} {key!r}: not a column ({', '.join(COLUMNS)}) nor a config key of any run"
        + _close(key, known)
    )


def _matches(value: Any, wanted: str) -> bool:
    """``--where`` equality: the YAML value (``true``, ``[64,64]``, ``3e-4``) or a text glob."""
    if value is None:
        return False
    try:
        parsed = yaml.load(wanted, Loader=_LOADER)
    except yaml.YAMLError:
        parsed = wanted
    if isinstance(value, (int, float)) and isinstance(parsed, str):
        try:
            parsed = float(parsed)
        except ValueError:
            pass
    from fnmatch import fnmatchcase

    return parsed == value or fnmatchcase(str(value), wanted)


def select(runs: list[Run], where: list[str] = (), statuses: list[str] = ()) -> list[Run]:
    """The runs that pass every ``KEY=VALUE`` / ``KEY!=VALUE`` and have one of ``statuses``."""
    out = runs
    for cond in where:
        neg = "!=" in cond
        key, sep, wanted = cond.partition("!=" if neg else "=")
        key = key.strip()
        if not sep or not key:
            raise RunsError(
                f"--where {cond!r}: write KEY=VALUE or KEY!=VALUE (e.g. env.name=hopper)"
            )
        check_key(key, runs, "--where")
        out = [r for r in out if _matches(_value(r, key), wanted.strip()) != neg]
    wanted_states = {s.strip() for group in statuses for s in group.split(",") if s.strip()}
    if wanted_states:
        out = [r for r in out if r.status in wanted_states]
    return out


def _orderable(value: Any) -> tuple:
    """Numbers before text, so that a config key holding both still sorts."""
    if isinstance(value, (int, float)):
        try:
            return (0, float(value), "")
        except OverflowError:  # an int beyond float's range (a hostile config value)
            return (0, float("inf") if value > 0 else float("-inf"), "")
    return (1, 0.0, str(value))


def sort_runs(runs: list[Run], spec: str) -> list[Run]:
    """Sort by ``KEY[,KEY...]`` (``-KEY``: descending); runs without a value go last either way."""
    out = list(runs)
    for part in reversed([p.strip() for p in spec.split(",") if p.strip()]):
        key, desc = part.lstrip("-"), part.startswith("-")
        check_key(key, runs, "--sort")
        values = {id(r): _value(r, key) for r in out}
        have = sorted(
            (r for r in out if values[id(r)] is not None),
            key=lambda r: _orderable(values[id(r)]),
            reverse=desc,
        )
        out = have + [r for r in out if values[id(r)] is None]
    return out


def print_runs(runs: list[Run]) -> None:
    """The table, a count per status, and for each died run why and how to resume it."""
    right = {i for i, k in enumerate(COLUMNS) if k in NUMERIC}
    print_table(list(COLUMNS), [cells(r) for r in runs], right)
    counts: dict[str, int] = {}
    for r in runs:
        counts[r.status] = counts.get(r.status, 0) + 1
    print(f"\n{len(runs)} run(s): " + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())))
    if any(not r.best_exact for r in runs):
        print(
            f">=: best over the last {TAIL_BYTES // 1024} KiB of metrics.jsonl only "
            "(a run without heartbeat.json)"
        )
    for r in runs:
        if r.status in ("died", "stalled", "running?"):
            print(f"\n{r.status}: {_rel(r.path)}: {r.note}")
        if r.resume:
            print(f"  resume: {r.resume}")
    members = [r for r in runs if r.hyperparameters]
    if members:
        print("\nPBT members' current hyperparameters:")
        for r in members:
            print(
                f"  {_rel(r.path)}: "
                + ", ".join(f"{k}={v:.4g}" for k, v in r.hyperparameters.items())
            )


def main(
    dirs: list[str],
    metric: str = DEFAULT_METRIC,
    sort: str = "start,dir",
    where: list[str] = (),
    statuses: list[str] = (),
    as_json: bool = False,
) -> None:
    """``rlexp runs``: RunsError (one line) for a missing dir or an unknown key."""
    for s in (s.strip() for group in statuses for s in group.split(",")):
        if s and s not in STATES:
            raise RunsError(f"--status {s!r}: choose from {', '.join(STATES)}" + _close(s, STATES))
    roots = [Path(d) for d in dirs] or [Path(d) for d in DEFAULT_DIRS if Path(d).is_dir()]
    found = read_runs(roots, metric)
    runs = sort_runs(select(found, list(where), list(statuses)), sort)
    warn_problems(found, "runs")  # after --where/--sort: they may read configs
    if as_json:
        print(json.dumps([r.to_json() for r in runs], indent=2))
    elif not runs:
        searched = ", ".join(str(r) for r in roots) or " and ".join(f"{d}/" for d in DEFAULT_DIRS)
        print(f"no runs under {searched}")
    else:
        print_runs(runs)
