"""The job dirs of a sweep as ``rlexp report`` reads them: a ``Job`` per dir with its overrides,
state, budget and metric histories. A file of the wrong shape (a torn ``metrics.jsonl`` line, a
``status.json`` that is not an object) is read as far as it goes and named in ``Job.problems``.

No numpy here: ``rlexp runs`` takes DEFAULT_METRIC and ``json_number`` from this module.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: The metric whose last value is a job's final score, and whose history is its learning curve.
DEFAULT_METRIC = "eval/episode_return"
#: Override keys that name a seed rather than a configuration.
SEED_KEYS = ("seed",)
#: Time inside the training loop per iteration (summed: requeue waits and startup don't count).
TIME_KEYS = ("perf/collect_time", "perf/update_time", "perf/eval_time")
#: The state of a job a hook ended before its budget (``rlexp.hooks``): a result, not a failure.
STOPPED_EARLY = "stopped_early"


@dataclass
class Job:
    """One job of the sweep: its dir, overrides, status and metric history."""

    path: Path
    overrides: list[str]
    seed: str | None
    # finished | stopped_early | running | stopped | interrupted | failed | missing | unreadable
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
        return self.state == STOPPED_EARLY

    @property
    def result(self) -> bool:
        """It enters the statistics: finished or stopped early, with a final value of the metric."""
        return self.state in ("finished", STOPPED_EARLY) and self.final is not None

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
    return float(value)


def _json_type(value: Any) -> str:
    """The JSON name of a parsed value's type (for messages about a file's shape)."""
    names = {dict: "object", list: "array", str: "string", bool: "boolean", type(None): "null"}
    return names.get(type(value), "number")


def _step(value: Any) -> int | None:
    """A step: a whole, non-negative JSON number."""
    x = json_number(value)
    return int(x) if x is not None and math.isfinite(x) and x >= 0 and x == int(x) else None


def _read_text(path: Path) -> str:
    """A file's text; bytes that are not UTF-8 (a torn write) become U+FFFD, not an error."""
    return path.read_bytes().decode("utf-8", errors="replace")


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
    try:
        lines = _read_text(path).splitlines()
    except FileNotFoundError:
        return {m: [] for m in metrics}, 0.0
    except OSError as exc:
        if problems is not None:
            problems.append(f"{path.name}: not readable ({exc.strerror or exc})")
        return {m: [] for m in metrics}, 0.0
    bad: list[tuple[int, str]] = []
    for num, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except ValueError:
            bad.append((num, "not JSON (a line cut short by a kill?)"))
            continue
        if not isinstance(row, dict):
            bad.append((num, f"a JSON {_json_type(row)}, not an object"))
            continue
        step = _step(row.get("step"))
        if step is None:
            bad.append((num, f"step {row.get('step')!r} is not a whole number"))
            continue
        wrong = [
            k
            for k in (*metrics, *TIME_KEYS)
            if row.get(k) is not None and json_number(row[k]) is None
        ]
        if wrong:
            bad.append((num, f"{wrong[0]} {row[wrong[0]]!r} is not a number"))
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
    if bad and problems is not None:
        num, why = bad[0]
        problems.append(f"{path.name}: {len(bad)} line(s) skipped (first: line {num}, {why})")
    if logged_at is not None:
        logged_at.update(at)
    return {m: sorted(v.items()) for m, v in values.items()}, float(sum(times.values()))


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
    try:
        status = json.loads(_read_text(path))
    except FileNotFoundError:
        return {}
    except OSError as exc:
        problems.append(f"status.json: not readable ({exc.strerror or exc})")
        return None
    except ValueError:
        problems.append("status.json: not JSON")
        return None
    if not isinstance(status, dict):
        problems.append(f"status.json: a JSON {_json_type(status)}, not an object")
        return None
    return status


def read_overrides(path: Path, problems: list[str]) -> list[str]:
    """A job's ``.hydra/overrides.yaml`` (a list of ``key=value``); [] and a problem otherwise."""
    from omegaconf import OmegaConf

    try:
        data = OmegaConf.to_container(OmegaConf.load(path))
    except (
        Exception
    ) as exc:  # a YAML or OmegaConf error, a torn file: the report goes on without it
        problems.append(f".hydra/overrides.yaml: not readable ({first_line(exc)})")
        return []
    if data is None:
        return []
    if not isinstance(data, list):
        problems.append(f".hydra/overrides.yaml: a {type(data).__name__}, not a list")
        return []
    return [str(o) for o in data]


def _running_reason(job_dir: Path, status: dict[str, Any]) -> str:
    """A ``running`` status.json checked against the job's heartbeat and PID, as ``rlexp runs``
    does: a job still training (the sweep goes on) is not called dead."""
    import time

    from rlexp.liveness import Here, liveness
    from rlexp.rundir import read_heartbeat

    shown, why = liveness(status, read_heartbeat(job_dir), time.time(), Here.now())
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
            problems.append(f"status.json: global_step {status['global_step']!r} is not a number")
        step = curve[-1][0] if curve else 0
    reason = status.get("reason") or ""
    if state == "running" and not reason:
        reason = _running_reason(job_dir, status)
    budget, env, backend = _budget_and_env(job_dir, problems)
    start = read_start(job_dir)
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
    import yaml

    for name in ("config.yaml", ".hydra/config.yaml"):
        path = job_dir / name
        try:
            cfg = yaml.load(_read_text(path), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
        except FileNotFoundError:
            continue
        except (OSError, yaml.YAMLError) as exc:
            problems.append(f"{name}: not readable ({first_line(exc)})")
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


def read_start(job_dir: Path) -> float | None:
    """The run's start (``provenance.json`` ``start_time``, whole seconds, rewritten by each
    attempt of a resumed run) as epoch seconds; None when it is missing or unreadable."""
    from rlexp.liveness import parse_time

    try:
        prov = json.loads(_read_text(job_dir / "provenance.json"))
    except (OSError, ValueError):
        return None
    return parse_time(prov.get("start_time")) if isinstance(prov, dict) else None


def wall_of(start: float | None, status: dict[str, Any]) -> float | None:
    """Seconds from the run's start (``read_start``) to its last ``status.json`` write (its end,
    for a job that ended), as ``rlexp runs`` shows a run's wall time; None when either is missing
    or unreadable."""
    from rlexp.liveness import parse_time

    end = parse_time(status.get("time"))
    return end - start if start is not None and end is not None and end >= start else None


def find_jobs(
    sweep_dir: Path, metric: str | None = DEFAULT_METRIC, other_metrics: Sequence[str] = ()
) -> list[Job]:
    """Every job dir under ``sweep_dir`` (one with ``.hydra/overrides.yaml``), in job-number order."""
    jobs = []
    for ov_file in sweep_dir.rglob(".hydra/overrides.yaml"):
        job_dir = ov_file.parent.parent
        if ".submitit" in job_dir.relative_to(sweep_dir).parts:
            continue
        jobs.append(read_job(job_dir, metric, other_metrics))

    def order(job: Job) -> tuple:
        rel = job.path.relative_to(sweep_dir).parts
        return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in rel)

    return sorted(jobs, key=order)
