"""The job dirs of a sweep as ``rlexp report`` reads them: a ``Job`` per dir with its overrides,
state, budget and metric histories. A file of the wrong shape (a torn ``metrics.jsonl`` line, a
``status.json`` that is not an object) is read as far as it goes and named in ``Job.problems``.

No numpy here: ``rlexp runs`` takes DEFAULT_METRIC and ``json_number`` from this module.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rlexp.files import safe_read

#: The metric whose last value is a job's final score, and whose history is its learning curve.
DEFAULT_METRIC = "eval/episode_return"
#: Override keys that name a seed rather than a configuration.
SEED_KEYS = ("seed",)
#: Time inside the training loop per iteration (summed: requeue waits and startup don't count).
TIME_KEYS = ("perf/collect_time", "perf/update_time", "perf/eval_time")
#: The state of a job a hook ended before its budget (``rlexp.hooks``): a result, not a failure.
STOPPED_EARLY = "stopped_early"
#: An Optuna trial its pruner stopped (a hook's stop too: its value at the stop is its result).
PRUNED = "pruned"
#: Distinct steps read at most from one ``metrics.jsonl`` (memory: ~100 bytes a step and metric).
MAX_STEPS = 2_000_000
#: Dirs inside a sweep that hold no job (their files are many: not walked).
NOT_JOBS = frozenset({".hydra", ".submitit", "tensorboard", "checkpoints", "wandb", "__pycache__"})


@dataclass
class Job:
    """One job of the sweep: its dir, overrides, status and metric history."""

    path: Path
    overrides: list[str]
    seed: str | None
    # finished | stopped_early | pruned | running | stopped | interrupted | failed | missing | unreadable
    state: str
    global_step: int
    reason: str = ""
    budget: int | None = None  # env steps the job was to train (its config), None: not known
    curve: list[tuple[int, float]] = field(default_factory=list)  # (step, metric), one per step
    time_s: float = 0.0
    curves: dict[str, list[tuple[int, float]]] = field(default_factory=dict)  # every metric read
    # per metric read, per step: the ``time`` of the row its value comes from (rows without one:
    # left out), e.g. when a job first reached a return
    logged_at: dict[str, dict[int, float]] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)  # what in its files could not be read
    env: str | None = None  # env.name of its config (e.g. Hopper-v5), None: no readable config
    backend: str | None = None  # env.backend of its config: gymnasium | native
    wall_s: float | None = None  # provenance.json start_time -> status.json time, as rlexp runs
    start: float | None = None  # provenance.json start_time, epoch seconds (a resume: its last)

    @property
    def final(self) -> float | None:
        """The metric's last logged value (the job's final eval), or None when it never evaluated."""
        return self.curve[-1][1] if self.curve else None

    @property
    def finished(self) -> bool:
        return self.state == "finished" and self.final is not None

    @property
    def stopped_early(self) -> bool:
        """A hook ended it before its budget: a result (its final eval is the value at the stop)."""
        return self.state in (STOPPED_EARLY, PRUNED)

    @property
    def result(self) -> bool:
        """It enters the statistics: finished or stopped early, with a final value of the metric."""
        return self.state in ("finished", STOPPED_EARLY, PRUNED) and self.final is not None

    @property
    def saved(self) -> int | None:
        """Env steps a stop left of the budget (0 for other jobs; None: the budget is not known)."""
        if not self.stopped_early:
            return 0
        return max(0, self.budget - self.global_step) if self.budget is not None else None

    @property
    def why(self) -> str:
        """Why the job did not finish, in a few words (its ``status.json`` reason when it has one)."""
        if self.reason:
            return self.reason
        if self.state == "missing":
            return "no status.json: the job ended before training or was killed"
        if self.state == "running":
            return "status.json still says running: the job was killed or its node died"
        if self.state == "unreadable":
            return next((p for p in self.problems if p.startswith("status.json")), "status.json")
        return f"state {self.state}"


def split_override(override: str) -> tuple[str, str]:
    key, _, value = override.partition("=")
    return key.lstrip("+~"), value


def first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def json_number(value: Any) -> float | None:
    """A JSON number as float; None for anything else (a string, a list, true/false, null)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        return float(value)
    except OverflowError:  # an integer beyond float's range (10**400): not a usable number
        return None


def _json_type(value: Any) -> str:
    """The JSON name of a parsed value's type (for messages about a file's shape)."""
    names = {dict: "object", list: "array", str: "string", bool: "boolean", type(None): "null"}
    return names.get(type(value), "number")


def _step(value: Any) -> int | None:
    """A step: a whole, non-negative JSON number."""
    x = json_number(value)
    return int(x) if x is not None and math.isfinite(x) and x >= 0 and x == int(x) else None


def _load_json(path: Path, problems: list[str]) -> Any:
    """A run-dir JSON file through ``rlexp.files.safe_read`` (a regular file, bounded in size and depth;
    bytes that are not UTF-8 become U+FFFD): {} when there is none, None (and a problem) when it
    cannot be read or is not JSON."""
    try:
        data = safe_read.read_bytes(path)
        return {} if data is None else safe_read.parse_json(data)
    except safe_read.Unreadable as exc:
        why = "not JSON" if str(exc).startswith("not JSON") else str(exc)
        problems.append(f"{path.name}: {why}")
        return None


def read_metrics(
    path: Path, metric: str, problems: list[str] | None = None
) -> tuple[list[tuple[int, float]], float]:
    """``metrics.jsonl`` -> the metric's history (last row per step wins: a resumed attempt may
    re-log steps after its checkpoint) and the summed training-loop time. Lines of the wrong shape
    (not a JSON object, no whole ``step``, a metric that is not a number) are skipped and counted
    into ``problems``."""
    histories, time_s = read_histories(path, (metric,), problems)
    return histories[metric], time_s


def read_histories(
    path: Path,
    metrics: Sequence[str],
    problems: list[str] | None = None,
    logged_at: dict[str, dict[int, float]] | None = None,
) -> tuple[dict[str, list[tuple[int, float]]], float]:
    """``read_metrics`` for several metrics in one pass over the file: each one's history.
    ``logged_at`` (when given) gets, per metric and step, the ``time`` (epoch seconds) of the row
    the value comes from; steps whose row has none (an older rlexp) are left out."""
    values: dict[str, dict[int, float]] = {m: {} for m in metrics}
    at: dict[str, dict[int, float]] = {m: {} for m in metrics}
    times: dict[int, float] = {}
    bad: list[tuple[int, str]] = []
    try:  # a regular file only, line by line, each line bounded (rlexp.files.safe_read)
        with safe_read.open_regular(path) as opened:
            stop = _read_rows(opened, metrics, (values, at, times), bad) if opened else ""
    except safe_read.Unreadable as exc:  # a FIFO, a device, a dir: nothing read
        stop = str(exc)
    except OSError as exc:  # an I/O error part way: what was read counts
        stop = f"not readable ({exc.strerror or exc})"
    if stop and problems is not None:
        problems.append(f"{path.name}: {stop}")
    if bad and problems is not None:
        num, why = bad[0]
        problems.append(f"{path.name}: {len(bad)} line(s) skipped (first: line {num}, {why})")
    if logged_at is not None:
        logged_at.update(at)
    return {m: sorted(v.items()) for m, v in values.items()}, float(sum(times.values()))


def _read_rows(
    opened: tuple[Any, int],
    metrics: Sequence[str],
    into: tuple[dict[str, dict[int, float]], dict[str, dict[int, float]], dict[int, float]],
    bad: list[tuple[int, str]],
) -> str:
    """The rows of an open ``metrics.jsonl`` into (values, logged_at, loop times) per step; lines
    of the wrong shape into ``bad``. Returns why it stopped early ("" at the end of the file)."""
    values, at, times = into
    for num, line in enumerate(safe_read.iter_lines(*opened), 1):
        if line is None:
            bad.append((num, f"longer than {safe_read.MAX_LINE >> 20} MiB"))
            continue
        text = line.decode("utf-8", errors="replace")  # a torn write: U+FFFD, not an error
        if not text.strip():
            continue
        try:
            row = json.loads(text)
        except RecursionError:
            bad.append((num, "nested too deep"))
            continue
        except ValueError:
            bad.append((num, "not JSON (a line cut short by a kill?)"))
            continue
        if not isinstance(row, dict):
            bad.append((num, f"a JSON {_json_type(row)}, not an object"))
            continue
        step = _step(row.get("step"))
        if step is None:
            bad.append((num, f"step {safe_read.shown(row.get('step'))} is not a whole number"))
            continue
        wrong = [
            k
            for k in (*metrics, *TIME_KEYS)
            if row.get(k) is not None and json_number(row[k]) is None
        ]
        if wrong:
            bad.append((num, f"{wrong[0]} {safe_read.shown(row[wrong[0]])} is not a number"))
        when = json_number(row.get("time"))
        for metric in metrics:
            value = json_number(row.get(metric))
            if value is not None and math.isfinite(value):
                values[metric][step] = value
                if when is not None and math.isfinite(when):
                    at[metric][step] = when
                else:
                    at[metric].pop(step, None)
        if any(k in row for k in TIME_KEYS):
            parts = [json_number(row.get(k)) for k in TIME_KEYS]
            times[step] = sum(p for p in parts if p is not None and math.isfinite(p))
        if len(times) > MAX_STEPS or any(len(v) > MAX_STEPS for v in values.values()):
            return f"more than {MAX_STEPS} logged steps: read up to line {num}"
    return ""


def add_histories(jobs: Sequence[Job], metrics: Sequence[str]) -> None:
    """Read the histories of ``metrics`` a job's ``Job.curves`` lacks from its ``metrics.jsonl``
    (a second view of jobs already read: the file's bad lines were counted the first time)."""
    for job in jobs:
        missing = [m for m in metrics if m not in job.curves]
        if missing:
            curves, _ = read_histories(job.path / "metrics.jsonl", missing, None, job.logged_at)
            job.curves.update(curves)


def read_status(path: Path, problems: list[str]) -> dict[str, Any] | None:
    """A job's ``status.json``: {} when there is none, None (and a problem) when it is not a JSON
    object."""
    status = _load_json(path, problems)
    if status is None:
        return None
    if not isinstance(status, dict):
        problems.append(f"status.json: a JSON {_json_type(status)}, not an object")
        return None
    return status


def read_overrides(path: Path, problems: list[str]) -> list[str]:
    """A job's ``.hydra/overrides.yaml`` (a list of ``key=value``); [] and a problem otherwise
    (also for a FIFO, a huge file, YAML aliases: ``rlexp.files.safe_read``)."""
    try:
        return safe_read.read_overrides(path)
    except safe_read.Unreadable as exc:
        why = str(exc) if str(exc).startswith("a ") else f"not readable ({exc})"
        problems.append(f".hydra/overrides.yaml: {why}")
        return []


def _running_reason(job_dir: Path, status: dict[str, Any], problems: list[str]) -> str:
    """A ``running`` status.json checked against the job's heartbeat and PID, as ``rlexp runs``
    does: a job still training (the sweep goes on) is not called dead. Both files' fields are
    checked first (``rlexp.files.safe_read``): a bad heartbeat is left out, a bad status cannot tell."""
    import time

    from rlexp.analysis.liveness import Here, liveness

    try:
        safe_read.check_fields(status, safe_read.STATUS_FIELDS)
    except safe_read.Unreadable as exc:
        return f"status.json says running, but {exc}"
    try:
        beat = safe_read.read_checked(job_dir / "heartbeat.json", safe_read.HEARTBEAT_FIELDS)
    except safe_read.Unreadable as exc:
        problems.append(f"heartbeat.json: {exc}")
        beat = {}
    shown, why = liveness(status, beat, time.time(), Here.now())
    if shown == "running":
        return "still running (its heartbeat is fresh): the sweep is not done"
    return f"{shown}: {why}" if why else shown


def read_job(job_dir: Path, metric: str | None, other_metrics: Sequence[str] = ()) -> Job:
    """One job dir; ``metric`` None skips ``metrics.jsonl`` (the state alone is wanted).
    ``other_metrics``: histories read besides ``metric``'s (into ``Job.curves``)."""
    problems: list[str] = []
    overrides = read_overrides(job_dir / ".hydra" / "overrides.yaml", problems)
    seed = next((v for k, v in map(split_override, overrides) if k in SEED_KEYS), None)
    status = read_status(job_dir / "status.json", problems)
    curve, time_s, curves, logged_at = [], 0.0, {}, {}
    if metric is not None:
        names = [metric, *(m for m in other_metrics if m != metric)]
        curves, time_s = read_histories(job_dir / "metrics.jsonl", names, problems, logged_at)
        curve = curves[metric]
    if status is None:
        state, status = "unreadable", {}
    elif not status:
        state = "missing"
    elif isinstance(status.get("state"), str):
        state = status["state"]
    else:
        state = "unreadable"
        problems.append(f"status.json: state {status.get('state')!r} is not a string")
    step = _step(status.get("global_step"))
    if step is None:
        if "global_step" in status:
            shown = safe_read.shown(status["global_step"])
            problems.append(f"status.json: global_step {shown} is not a number")
        step = curve[-1][0] if curve else 0
    reason = status.get("reason") or ""
    if state == "running" and not reason:
        reason = _running_reason(job_dir, status, problems)
    budget, env, backend = _budget_and_env(job_dir, problems)
    start = read_start(job_dir, problems)
    return Job(
        budget=budget,
        env=env,
        backend=backend,
        wall_s=wall_of(start, status),
        start=start,
        path=job_dir,
        overrides=overrides,
        seed=seed,
        state=state,
        global_step=step,
        reason=reason if isinstance(reason, str) else json.dumps(reason),
        curve=curve,
        time_s=time_s,
        curves=curves,
        logged_at=logged_at,
        problems=problems,
    )


def _budget_of(cfg: Any) -> int | None:
    """``trainer.total_frames``, or ``trainer.iterations`` x ``frames_per_batch`` when set (as
    ``rlexp.config.validate.total_frames`` for one process), from a plain config mapping."""
    trainer = cfg.get("trainer") if isinstance(cfg, dict) else None
    if not isinstance(trainer, dict):
        return None
    if trainer.get("iterations") is not None:
        iterations, batch = _step(trainer.get("iterations")), _step(trainer.get("frames_per_batch"))
        return iterations * batch if iterations is not None and batch is not None else None
    return _step(trainer.get("total_frames"))


def _configs(job_dir: Path, problems: list[str]) -> Iterator[dict]:
    """The job's configs as plain mappings, read one by one as asked for: its ``config.yaml`` (the
    resolved config rlexp writes once training starts), then Hydra's ``.hydra/config.yaml``."""
    for name in ("config.yaml", ".hydra/config.yaml"):
        try:  # bounded, no aliases, safe tags only (rlexp.files.safe_read)
            cfg = safe_read.load_yaml(job_dir / name)
        except safe_read.Unreadable as exc:
            problems.append(f"{name}: not readable ({exc})")
            continue
        if isinstance(cfg, dict):
            yield cfg


def read_budget(job_dir: Path, problems: list[str]) -> int | None:
    """The env steps a job was to train, from its ``config.yaml`` or else Hydra's
    ``.hydra/config.yaml``; None when neither says (a job that ended before training writes
    neither)."""
    return next((b for b in map(_budget_of, _configs(job_dir, problems)) if b is not None), None)


def _env_of(cfg: dict) -> tuple[str | None, str | None]:
    """(``env.name``, ``env.backend``) of a plain config mapping; None where it does not say."""
    env = cfg.get("env")
    if not isinstance(env, dict) or not isinstance(env.get("name"), str):
        return None, None
    backend = env.get("backend")
    return env["name"], backend if isinstance(backend, str) else None


def _budget_and_env(
    job_dir: Path, problems: list[str]
) -> tuple[int | None, str | None, str | None]:
    """``read_budget`` and the env (``env.name``, ``env.backend``) in one read of the configs: each
    from the first config that says, each file read once."""
    budget, env, backend = None, None, None
    for cfg in _configs(job_dir, problems):
        budget = budget if budget is not None else _budget_of(cfg)
        if env is None:
            env, backend = _env_of(cfg)
        if budget is not None and env is not None:
            break
    return budget, env, backend


def read_start(job_dir: Path, problems: list[str] | None = None) -> float | None:
    """The run's start (``provenance.json`` ``start_time``, whole seconds, rewritten by each
    attempt of a resumed run) as epoch seconds; None when it is missing or unreadable (and then a
    problem)."""
    from rlexp.analysis.liveness import parse_time

    prov = _load_json(job_dir / "provenance.json", problems if problems is not None else [])
    return parse_time(prov.get("start_time")) if isinstance(prov, dict) else None


def wall_of(start: float | None, status: dict[str, Any]) -> float | None:
    """Seconds from the run's start (``read_start``) to its last ``status.json`` write (its end,
    for a job that ended), as ``rlexp runs`` shows a run's wall time; None when either is missing
    or unreadable."""
    from rlexp.analysis.liveness import parse_time

    end = parse_time(status.get("time"))
    return end - start if start is not None and end is not None and end >= start else None


def find_jobs(
    sweep_dir: Path, metric: str | None = DEFAULT_METRIC, other_metrics: Sequence[str] = ()
) -> list[Job]:
    """Every job dir under ``sweep_dir`` (one with ``.hydra/overrides.yaml``), in job-number order;
    symlinked job dirs are followed, each job read once (``rlexp.files.dirwalk``)."""
    from rlexp.files.dirwalk import find_dirs

    def is_job(here: Path, names: set[str]) -> bool:
        return ".hydra" in names and os.path.lexists(here / ".hydra" / "overrides.yaml")

    job_dirs = find_dirs([sweep_dir], is_job, lambda name: name in NOT_JOBS, inside_wanted=True)
    jobs = [read_job(job_dir, metric, other_metrics) for job_dir in job_dirs]

    def order(job: Job) -> tuple:
        rel = job.path.relative_to(sweep_dir).parts
        return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in rel)

    return sorted(jobs, key=order)
