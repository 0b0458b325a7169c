"""``rlexp report SWEEP_DIR``: per-configuration statistics and learning curves of a Hydra sweep.

A configuration is a job's overrides (``.hydra/overrides.yaml``) less the seed; its seeds are the
jobs that share it. For each configuration: the final eval return over seeds (mean +- std, and the
interquartile mean with a 95% bootstrap confidence interval, as rliable recommends for few seeds),
steps and training time; with ``--threshold``, how many seeds reached a level of a metric and the
median and IQM of the steps they took (once, and IN_A_ROW logged values in a row). Jobs a hook
ended early (``stopped_early``, e.g. the median stopping rule) are results: their value at the stop
enters the statistics, their configuration counts them, and they are listed apart with the budget
they saved. The jobs the sweep was to run come from its ``multirun.yaml`` (the basic sweeper's
grid, Optuna's ``n_trials``): jobs whose ``status.json`` is missing or neither ``finished`` nor
``stopped_early``, and jobs that never started, are listed apart, never silently dropped. A file
of the wrong shape (a torn ``metrics.jsonl`` line, a ``status.json`` that is not an object) is
read as far as it goes and named in the report. Writes ``report.md``, ``report.csv`` and
``curves.png`` into the sweep dir; a sweep dir that cannot be written gets one line saying so, and
the report is still returned.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)

#: The metric whose last value is a job's final score, and whose history is its learning curve.
DEFAULT_METRIC = "eval/episode_return"
#: Override keys that name a seed rather than a configuration.
SEED_KEYS = ("seed",)
#: Time inside the training loop per iteration (summed: requeue waits and startup don't count).
TIME_KEYS = ("perf/collect_time", "perf/update_time", "perf/eval_time")
#: A plan's source when Hydra's parser could not expand the sweep's overrides.
UNEXPANDED = "the sweep's overrides could not be expanded"
#: ``hydra.sweep.subdir`` that names each job dir after its job number (conf/config.yaml).
JOB_NUM_SUBDIR = "${hydra.job.num}"
#: Consecutive logged values at or above a threshold that count as holding it, not a lucky eval.
IN_A_ROW = 3
#: The state of a job a hook ended before its budget (``rlexp.hooks``): a result, not a failure.
STOPPED_EARLY = "stopped_early"
#: The study of an Optuna sweep (``rlexp.launch.optuna_sweeper.STUDY_FILE``): its trials are listed.
OPTUNA_STUDY = "optuna.db"


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
    problems: list[str] = field(default_factory=list)  # what in its files could not be read

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


@dataclass(frozen=True)
class Threshold:
    """A level of ``metric`` whose first crossing measures how fast a seed learns."""

    metric: str
    value: float


def parse_threshold(text: str) -> tuple[str | None, float]:
    """``--threshold``'s argument: ``VALUE`` (in the report's metric) or ``METRIC=VALUE``."""
    metric, sep, value = text.rpartition("=")
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not math.isfinite(number) or (sep and not metric.strip()):
        raise ValueError(
            f"{text!r} is not VALUE or METRIC=VALUE with a finite number "
            "(e.g. 475, or eval/success_rate=0.9)"
        )
    return metric.strip() or None, number


@dataclass
class ThresholdStats:
    """Steps to a threshold for each seed of a configuration with a result (finished or stopped
    early; None: never reached)."""

    threshold: Threshold
    first: list[int | None]  # the first logged value at or above it
    in_a_row: list[int | None]  # the first of IN_A_ROW consecutive logged values at or above it

    @property
    def n(self) -> int:
        return len(self.first)


@dataclass
class ConfigStats:
    """The jobs of one configuration and their statistics over seeds."""

    label: str
    jobs: list[Job]
    finals: np.ndarray
    mean: float
    std: float
    iqm: float
    iqm_ci: tuple[float, float]
    mean_ci: tuple[float, float]
    steps: float
    time_s: float
    threshold: ThresholdStats | None = None

    @property
    def n_unfinished(self) -> int:
        """Jobs out of the statistics: failed, killed, or finished without the metric."""
        return sum(not j.result and not j.stopped_early for j in self.jobs)

    @property
    def n_stopped_early(self) -> int:
        """Jobs a hook stopped (those with the metric are among the seeds, at their value then)."""
        return sum(j.stopped_early for j in self.jobs)


@dataclass(frozen=True)
class ExpectedJob:
    """A job that the sweep's ``multirun.yaml`` says it launches."""

    num: int  # hydra.job.num
    overrides: tuple[str, ...] | None  # None where the sweeper picks them as it goes (Optuna)

    @property
    def label(self) -> str:
        return " ".join(self.overrides) if self.overrides is not None else "(chosen by the sweeper)"


@dataclass
class Plan:
    """The jobs a sweep was to launch (None: not known), and where that number comes from."""

    jobs: list[ExpectedJob] | None
    source: str
    numbered_dirs: bool = True  # job dirs are named by job number (hydra.sweep.subdir)


@dataclass
class Sweep:
    """A sweep dir's job dirs against its plan."""

    jobs: list[Job]  # every job dir found
    plan: Plan
    never_started: list[ExpectedJob]  # planned, no job dir
    extra: list[Job]  # job dirs the plan does not name (an earlier sweep into the same dir)

    @property
    def planned(self) -> list[Job]:
        """The job dirs of this sweep (all of them when the plan is unknown)."""
        extra = {id(j) for j in self.extra}
        return [j for j in self.jobs if id(j) not in extra]


@dataclass(frozen=True)
class BudgetSaved:
    """Env steps that early stops left untrained, against the budget of every job dir."""

    saved: int  # sum over stopped-early jobs of budget - steps done
    total: int  # sum of the budgets of the job dirs whose budget is known
    n_unknown: int  # job dirs whose budget is not known (no readable config): in neither sum

    @property
    def share(self) -> float:
        return self.saved / self.total if self.total else math.nan

    def describe(self) -> str:
        """``49152 env steps, 37.5% of the sweep's 131072``, and what could not be counted."""
        text = f"{self.saved} env steps, {_fmt(100 * self.share, 1)}% of the sweep's {self.total}"
        if self.n_unknown:
            text += f" ({self.n_unknown} job dir(s) without a readable budget not counted)"
        return text


def budget_saved(jobs: Iterable[Job]) -> BudgetSaved:
    """What early stops saved: over stopped-early jobs, their budget less the steps they reached;
    as a share of the summed budget of ``jobs`` (every job dir of the sweep)."""
    saved = total = unknown = 0
    for job in jobs:
        if job.budget is None:
            unknown += 1
            continue
        total += job.budget
        saved += job.saved or 0
    return BudgetSaved(saved, total, unknown)


def _split(override: str) -> tuple[str, str]:
    key, _, value = override.partition("=")
    return key.lstrip("+~"), value


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _number(value: Any) -> float | None:
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
    x = _number(value)
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
    path: Path, metrics: Sequence[str], problems: list[str] | None = None
) -> tuple[dict[str, list[tuple[int, float]]], float]:
    """``read_metrics`` for several metrics in one pass over the file: each one's history."""
    values: dict[str, dict[int, float]] = {m: {} for m in metrics}
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
            k for k in (*metrics, *TIME_KEYS) if row.get(k) is not None and _number(row[k]) is None
        ]
        if wrong:
            bad.append((num, f"{wrong[0]} {row[wrong[0]]!r} is not a number"))
        for metric in metrics:
            value = _number(row.get(metric))
            if value is not None and math.isfinite(value):
                values[metric][step] = value
        if any(k in row for k in TIME_KEYS):
            parts = [_number(row.get(k)) for k in TIME_KEYS]
            times[step] = sum(p for p in parts if p is not None and math.isfinite(p))
    if bad and problems is not None:
        num, why = bad[0]
        problems.append(f"{path.name}: {len(bad)} line(s) skipped (first: line {num}, {why})")
    return {m: sorted(v.items()) for m, v in values.items()}, float(sum(times.values()))


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
    try:
        data = OmegaConf.to_container(OmegaConf.load(path))
    except (
        Exception
    ) as exc:  # a YAML or OmegaConf error, a torn file: the report goes on without it
        problems.append(f".hydra/overrides.yaml: not readable ({_first_line(exc)})")
        return []
    if data is None:
        return []
    if not isinstance(data, list):
        problems.append(f".hydra/overrides.yaml: a {type(data).__name__}, not a list")
        return []
    return [str(o) for o in data]


def read_job(job_dir: Path, metric: str | None, other_metrics: Sequence[str] = ()) -> Job:
    """One job dir; ``metric`` None skips ``metrics.jsonl`` (the state alone is wanted).
    ``other_metrics``: histories read besides ``metric``'s (into ``Job.curves``)."""
    problems: list[str] = []
    overrides = read_overrides(job_dir / ".hydra" / "overrides.yaml", problems)
    seed = next((v for k, v in map(_split, overrides) if k in SEED_KEYS), None)
    status = read_status(job_dir / "status.json", problems)
    curve, time_s, curves = [], 0.0, {}
    if metric is not None:
        names = [metric, *(m for m in other_metrics if m != metric)]
        curves, time_s = read_histories(job_dir / "metrics.jsonl", names, problems)
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
    return Job(
        budget=read_budget(job_dir, problems),
        path=job_dir,
        overrides=overrides,
        seed=seed,
        state=state,
        global_step=step,
        reason=reason if isinstance(reason, str) else json.dumps(reason),
        curve=curve,
        time_s=time_s,
        curves=curves,
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


def read_budget(job_dir: Path, problems: list[str]) -> int | None:
    """The env steps a job was to train, from its ``config.yaml`` (the resolved config rlexp
    writes) or else Hydra's ``.hydra/config.yaml``; None when neither says (a job that ended before
    training writes neither)."""
    import yaml

    for name in ("config.yaml", ".hydra/config.yaml"):
        path = job_dir / name
        try:
            cfg = yaml.load(_read_text(path), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
        except FileNotFoundError:
            continue
        except (OSError, yaml.YAMLError) as exc:
            problems.append(f"{name}: not readable ({_first_line(exc)})")
            continue
        budget = _budget_of(cfg)
        if budget is not None:
            return budget
    return None


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


def _plain(cfg: DictConfig, key: str) -> Any:
    """``cfg[key]`` as plain Python, resolved where it can be (a ``${now:}`` in a saved config
    cannot be: then as written)."""
    node = OmegaConf.select(cfg, key, throw_on_resolution_failure=False)
    if not OmegaConf.is_config(node):
        return node
    try:
        return OmegaConf.to_container(node, resolve=True)
    except Exception:  # an interpolation that only resolves inside the sweep
        return OmegaConf.to_container(node, resolve=False)


def plan_from_config(cfg: DictConfig, config_loader: Any = None) -> Plan:
    """The jobs a sweep launches, from its config (``multirun.yaml``): the basic sweeper's grid,
    expanded by Hydra's own ``BasicSweeper.split_arguments`` (job N = the N-th combination); Optuna:
    ``n_trials`` jobs. ``config_loader`` expands ``glob(...)`` over config groups."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    sweep = OmegaConf.select(cfg, "hydra.sweep")
    raw = OmegaConf.to_container(sweep, resolve=False) if isinstance(sweep, DictConfig) else {}
    numbered = raw.get("subdir") == JOB_NUM_SUBDIR
    target = str(_plain(cfg, "hydra.sweeper._target_") or "")
    if target.endswith(".BasicSweeper"):
        params = _plain(cfg, "hydra.sweeper.params") or {}
        task = _plain(cfg, "hydra.overrides.task") or []
        if not isinstance(params, dict) or not isinstance(task, list):
            return Plan(None, "hydra.sweeper.params / hydra.overrides.task are of the wrong shape")
        lines = [f"{k}={v}" for k, v in params.items()] + [str(o) for o in task]
        try:
            parsed = OverridesParser.create(config_loader=config_loader).parse_overrides(lines)
            batches = BasicSweeper.split_arguments(parsed, None)[0]
        except Exception as exc:  # Hydra's parser: a sweep it cannot expand without the configs
            return Plan(None, f"{UNEXPANDED} ({_first_line(exc)})")
        jobs = [ExpectedJob(i, tuple(o)) for i, o in enumerate(batches)]
        return Plan(jobs, "the grid of the sweep's overrides", numbered)
    if "optuna" in target.lower():
        n = _plain(cfg, "hydra.sweeper.n_trials")
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            return Plan(None, f"hydra.sweeper.n_trials={n!r} is not a number of trials")
        jobs = [ExpectedJob(i, None) for i in range(n)]
        return Plan(jobs, "hydra.sweeper.n_trials", numbered)
    return Plan(None, f"the sweeper {target or '(none)'} does not say how many jobs it launches")


def read_plan(sweep_dir: Path) -> Plan:
    """The plan of the sweep in ``sweep_dir``, from its ``multirun.yaml``."""
    path = sweep_dir / "multirun.yaml"
    try:
        cfg = OmegaConf.load(path)
    except FileNotFoundError:
        return Plan(None, "no multirun.yaml in the sweep dir")
    except Exception as exc:  # a YAML error, a torn file: the report goes on without a plan
        return Plan(None, f"multirun.yaml is not readable ({_first_line(exc)})")
    if not isinstance(cfg, DictConfig):
        return Plan(None, "multirun.yaml is not a mapping")
    plan = plan_from_config(cfg)
    if plan.jobs is None and plan.source.startswith(UNEXPANDED):
        plan = _plan_with_rlexp_configs(cfg) or plan
    return plan


def _plan_with_rlexp_configs(cfg: DictConfig) -> Plan | None:
    """The plan with rlexp's ``conf/`` at hand: a ``glob(...)`` over a config group lists the
    group's options (as the sweep did). None where Hydra is already set up in this process."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from rlexp.app import CONF_DIR
    from rlexp.config.schema import register_configs

    if GlobalHydra.instance().is_initialized():
        return None
    register_configs()  # the schemas are group options too, as in the sweep
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return plan_from_config(cfg, GlobalHydra.instance().config_loader())
    except Exception:  # Hydra's own errors: the plan stays unknown, with the first reason
        return None
    finally:
        GlobalHydra.instance().clear()


def match_plan(sweep_dir: Path, jobs: list[Job], plan: Plan) -> Sweep:
    """Which planned jobs have a dir: matched by overrides (a grid: Hydra writes each job's own
    overrides into its ``.hydra/overrides.yaml``), else by job number (the dir name)."""
    if plan.jobs is None:
        return Sweep(jobs, plan, [], [])
    by_overrides: dict[tuple[str, ...], list[Job]] = {}
    for job in jobs:
        by_overrides.setdefault(tuple(job.overrides), []).append(job)
    by_name = {job.path.relative_to(sweep_dir).as_posix(): job for job in jobs}
    in_order = iter(jobs)  # other dir names: trials start in job-number order
    never: list[ExpectedJob] = []
    claimed: set[int] = set()
    for expected in plan.jobs:
        if expected.overrides is not None:
            same = by_overrides.get(expected.overrides)
            found = same.pop(0) if same else None
        elif plan.numbered_dirs:
            found = by_name.get(str(expected.num))
        else:
            found = next(in_order, None)
        if found is None:
            never.append(expected)
        else:
            claimed.add(id(found))
    extra = [j for j in jobs if id(j) not in claimed]
    return Sweep(jobs, plan, never, extra)


def read_sweep(
    sweep_dir: Path,
    metric: str | None = DEFAULT_METRIC,
    plan: Plan | None = None,
    other_metrics: Sequence[str] = (),
) -> Sweep:
    """The job dirs of ``sweep_dir`` against ``plan`` (default: from its ``multirun.yaml``)."""
    jobs = find_jobs(sweep_dir, metric, other_metrics)
    return match_plan(sweep_dir, jobs, plan if plan is not None else read_plan(sweep_dir))


def config_key(job: Job) -> tuple[str, ...]:
    """A job's configuration: its overrides without the seed."""
    return tuple(o for o in job.overrides if _split(o)[0] not in SEED_KEYS)


def common_overrides(jobs: list[Job]) -> list[str]:
    """Overrides every job shares (shown once, not in every configuration's label)."""
    keys = [set(config_key(j)) for j in jobs]
    common = set.intersection(*keys) if keys else set()
    return [o for o in config_key(jobs[0]) if o in common] if jobs else []


def iqm(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean: the mean of the middle 50% (robust with few seeds)."""
    from scipy.stats import trim_mean

    return trim_mean(x, 0.25, axis=axis)


def bootstrap_ci(x: np.ndarray, statistic, seed: int = 0) -> tuple[float, float]:
    """95% percentile-bootstrap interval of ``statistic`` (NaN with fewer than two values)."""
    from scipy.stats import bootstrap

    if len(x) < 2:
        return math.nan, math.nan
    if np.all(x == x[0]):
        return float(x[0]), float(x[0])
    res = bootstrap(
        (x,),
        statistic,
        confidence_level=0.95,
        n_resamples=5000,
        method="percentile",
        vectorized=True,
        random_state=np.random.default_rng(seed),
    )
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def steps_to_threshold(
    points: Iterable[tuple[int, float | None]], threshold: float, in_a_row: int = 1
) -> int | None:
    """The step where a metric's history first holds at or above ``threshold`` for ``in_a_row``
    consecutive logged values (1: the first value that reaches it); None when it never does.
    ``points`` are (step, value) in any order; a missing or non-finite value is skipped (it neither
    counts nor breaks a run), and of two values at one step the later wins, as ``read_metrics``."""
    if in_a_row < 1:
        raise ValueError(f"in_a_row must be at least 1, got {in_a_row}")
    values: dict[int, float] = {}
    for step, value in points:
        if value is not None and math.isfinite(value):
            values[step] = value
    start, run = None, 0
    for step in sorted(values):
        if values[step] >= threshold:
            start = step if run == 0 else start
            run += 1
            if run == in_a_row:
                return start
        else:
            run = 0
    return None


def reached_stats(steps: Sequence[int | None]) -> tuple[int, float, float]:
    """How many seeds reached a threshold, and the median and IQM of their steps to it (NaN when
    none did). Seeds that never reached it are left out of both, and counted by the first number."""
    hit = np.array([s for s in steps if s is not None], dtype=float)
    if not len(hit):
        return 0, math.nan, math.nan
    return len(hit), float(np.median(hit)), float(iqm(hit))


def threshold_stats(jobs: list[Job], threshold: Threshold) -> ThresholdStats:
    """Steps to ``threshold`` for each job (its ``Job.curves`` must hold the threshold's metric)."""
    curves = [j.curves.get(threshold.metric, []) for j in jobs]
    return ThresholdStats(
        threshold=threshold,
        first=[steps_to_threshold(c, threshold.value) for c in curves],
        in_a_row=[steps_to_threshold(c, threshold.value, IN_A_ROW) for c in curves],
    )


def summarize(jobs: list[Job], threshold: Threshold | None = None) -> list[ConfigStats]:
    """Group jobs by configuration and compute the statistics over its results, finished and stopped
    early seeds alike (and their steps to ``threshold``)."""
    common = set(common_overrides(jobs))
    groups: dict[tuple[str, ...], list[Job]] = {}
    for job in jobs:
        groups.setdefault(config_key(job), []).append(job)
    stats = []
    for key, members in groups.items():
        done = [j for j in members if j.result]
        finals = np.array([j.final for j in done], dtype=float)
        label = " ".join(o for o in key if o not in common) or "(all jobs)"
        nan2 = (math.nan, math.nan)
        stats.append(
            ConfigStats(
                label=label,
                jobs=members,
                finals=finals,
                mean=float(finals.mean()) if len(finals) else math.nan,
                std=float(finals.std(ddof=1))
                if len(finals) > 1
                else (0.0 if len(finals) else math.nan),
                iqm=float(iqm(finals)) if len(finals) else math.nan,
                iqm_ci=bootstrap_ci(finals, iqm) if len(finals) else nan2,
                mean_ci=bootstrap_ci(finals, np.mean) if len(finals) else nan2,
                steps=float(np.mean([j.global_step for j in done])) if done else math.nan,
                time_s=float(np.mean([j.time_s for j in done])) if done else math.nan,
                threshold=threshold_stats(done, threshold) if threshold else None,
            )
        )
    return stats


def _fmt(x: float, digits: int = 2) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _cell(text: str) -> str:
    """Text for one markdown table cell (a reason may hold ``|`` or a newline)."""
    return " ".join(str(text).split()).replace("|", "\\|")


CSV_FIELDS = [
    "configuration",
    "n_seeds",
    "seeds",
    "final_mean",
    "final_std",
    "iqm",
    "iqm_ci_low",
    "iqm_ci_high",
    "mean_ci_low",
    "mean_ci_high",
    "steps",
    "time_s",
    "n_unfinished",
    "n_stopped_early",  # jobs a hook stopped; those with the metric are among n_seeds
    "seeds_stopped_early",
]
_ROW = f"_{IN_A_ROW}_in_a_row"
#: Columns added after CSV_FIELDS when the report has a threshold (``n_seeds`` is the n of k/n).
THRESHOLD_CSV_FIELDS = [
    "threshold_metric",
    "threshold",
    "n_reached",
    "steps_to_threshold_median",
    "steps_to_threshold_iqm",
    f"n_reached{_ROW}",
    f"steps_to_threshold{_ROW}_median",
    f"steps_to_threshold{_ROW}_iqm",
    "steps_to_threshold_per_seed",  # in the order of `seeds`; "none": never reached
    f"steps_to_threshold{_ROW}_per_seed",
]


def _threshold_row(t: ThresholdStats) -> dict[str, Any]:
    """The THRESHOLD_CSV_FIELDS of one configuration."""
    row: dict[str, Any] = {"threshold_metric": t.threshold.metric, "threshold": t.threshold.value}
    for suffix, steps in (("", t.first), (_ROW, t.in_a_row)):
        k, median, iqm_ = reached_stats(steps)
        row[f"n_reached{suffix}"] = k
        row[f"steps_to_threshold{suffix}_median"] = median
        row[f"steps_to_threshold{suffix}_iqm"] = iqm_
        row[f"steps_to_threshold{suffix}_per_seed"] = " ".join(
            "none" if x is None else str(x) for x in steps
        )
    return row


def to_csv(stats: list[ConfigStats]) -> str:
    """One row per configuration (with a threshold: its THRESHOLD_CSV_FIELDS too)."""
    with_threshold = any(s.threshold is not None for s in stats)
    fields = CSV_FIELDS + (THRESHOLD_CSV_FIELDS if with_threshold else [])
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for s in stats:
        writer.writerow(
            {
                "configuration": s.label,
                "n_seeds": len(s.finals),
                "seeds": " ".join(str(j.seed) for j in s.jobs if j.result),
                "final_mean": s.mean,
                "final_std": s.std,
                "iqm": s.iqm,
                "iqm_ci_low": s.iqm_ci[0],
                "iqm_ci_high": s.iqm_ci[1],
                "mean_ci_low": s.mean_ci[0],
                "mean_ci_high": s.mean_ci[1],
                "steps": s.steps,
                "time_s": s.time_s,
                "n_unfinished": s.n_unfinished,
                "n_stopped_early": s.n_stopped_early,
                "seeds_stopped_early": " ".join(str(j.seed) for j in s.jobs if j.stopped_early),
                **(_threshold_row(s.threshold) if s.threshold is not None else {}),
            }
        )
    return buf.getvalue()


def _counts(sweep: Sweep) -> str:
    """The first line of the report: how many jobs were expected, started, finished, failed."""
    jobs, plan = sweep.jobs, sweep.plan
    n_done = sum(j.finished for j in jobs)
    n_early = sum(j.stopped_early for j in jobs)
    n_bad = len(jobs) - n_done - n_early
    done = f"{n_done} finished, " + (f"{n_early} stopped early, " if n_early else "")
    if plan.jobs is None:
        text = (
            f"{len(jobs)} jobs (how many the sweep was to run is not known: {plan.source}), "
            f"{done}{n_bad} failed or unfinished."
        )
    else:
        text = (
            f"{len(plan.jobs)} jobs expected (multirun.yaml: {plan.source}), "
            f"{len(jobs) - len(sweep.extra)} started, {done}"
            f"{n_bad} failed or unfinished, {len(sweep.never_started)} never started."
        )
    if sweep.extra:
        text += (
            f" {len(sweep.extra)} job dir(s) are not among the jobs multirun.yaml lists (an "
            "earlier sweep into the same dir?); they are reported with the others."
        )
    return text


def to_markdown(sweep_dir: Path, sweep: Sweep, stats: list[ConfigStats], metric: str) -> str:
    """The human-readable report: configurations, jobs stopped early and the budget they saved,
    failed or unfinished jobs, jobs that never started, and the files that could only be read in
    part."""
    jobs = sweep.jobs
    early = [j for j in jobs if j.stopped_early]
    score = (
        f"the last `{metric}` of each finished job, and of each job stopped early (its value at "
        "the stop)"
        if early
        else f"the last `{metric}` of each finished job"
    )
    lines = [
        f"# Sweep report: `{sweep_dir}`",
        "",
        _counts(sweep),
        "",
        f"{len(stats)} configuration(s). Score: {score}. IQM: "
        "interquartile mean; CI: 95% percentile bootstrap over seeds. Time: seconds inside the "
        "training loop (collect + update + eval).",
        "",
    ]
    common = common_overrides(jobs)
    if common:
        lines += ["Shared overrides: `" + " ".join(common) + "`", ""]
    # The "stopped early" column only in sweeps that have such jobs: others read as they always did.
    lines += [
        "| configuration | seeds | final mean ± std | IQM [95% CI] | steps | time (s) | unfinished |"
        + (" stopped early |" if early else ""),
        "|---|---|---|---|---|---|---|" + ("---|" if early else ""),
    ]
    ranked = sorted(stats, key=lambda s: -s.iqm if not math.isnan(s.iqm) else math.inf)
    for s in ranked:
        lines.append(
            f"| `{s.label}` | {len(s.finals)} | {_fmt(s.mean)} ± {_fmt(s.std)} | {_fmt(s.iqm)} "
            f"[{_fmt(s.iqm_ci[0])}, {_fmt(s.iqm_ci[1])}] | {_fmt(s.steps, 0)} | {_fmt(s.time_s, 1)} "
            f"| {s.n_unfinished} |" + (f" {s.n_stopped_early} |" if early else "")
        )
    with_threshold = [s for s in ranked if s.threshold is not None]
    if with_threshold:
        lines += ["", *threshold_markdown(with_threshold)]
    if early:
        lines += ["", *stopped_early_markdown(sweep_dir, jobs, metric)]
    bad = [j for j in jobs if not j.result and not j.stopped_early]
    lines += ["", f"## Unfinished or failed jobs ({len(bad)})", ""]
    if bad:
        lines += ["| job | overrides | state | step | reason |", "|---|---|---|---|---|"]
        for j in bad:
            state = j.state if j.state != "finished" else f"finished, no `{metric}` logged"
            reason = j.why if j.state != "finished" else ""
            lines.append(
                f"| `{j.path.relative_to(sweep_dir)}` | `{' '.join(j.overrides)}` | {state} "
                f"| {j.global_step} | {_cell(reason)} |"
            )
    else:
        lines.append("None.")
    if sweep.plan.jobs is not None:
        lines += ["", f"## Never started ({len(sweep.never_started)})", ""]
        if sweep.never_started:
            lines += [
                "Expected from multirun.yaml, but no job dir: the sweep stopped before them.",
                "",
                "| job | overrides |",
                "|---|---|",
            ]
            lines += [f"| #{e.num} | `{e.label}` |" for e in sweep.never_started]
        else:
            lines.append("None.")
    damaged = [(j, p) for j in jobs for p in j.problems]
    if damaged:
        lines += ["", f"## Files read in part ({len(damaged)})", ""]
        for j, problem in damaged:
            name, _, what = problem.partition(": ")
            lines.append(f"- `{j.path.relative_to(sweep_dir) / name}`: {what}")
    return "\n".join(lines) + "\n"


def stopped_early_markdown(sweep_dir: Path, jobs: list[Job], metric: str) -> list[str]:
    """The jobs a hook stopped (dir, step reached, budget, value at the stop, reason) and the
    budget they saved."""
    early = [j for j in jobs if j.stopped_early]
    saved = budget_saved(jobs)
    lines = [
        f"## Stopped early ({len(early)})",
        "",
        "Ended by a hook (`hooks.*`, e.g. the median stopping rule) before their budget: results, "
        f"not failures. Their last `{metric}` (the value at the stop) is among the scores above.",
        "",
        f"| job | overrides | step | budget | final `{metric}` | reason |",
        "|---|---|---|---|---|---|",
    ]
    for j in early:
        budget = str(j.budget) if j.budget is not None else "n/a"
        final = _fmt(j.final) if j.final is not None else "n/a"
        lines.append(
            f"| `{j.path.relative_to(sweep_dir)}` | `{' '.join(j.overrides)}` | {j.global_step} "
            f"| {budget} | {final} | {_cell(j.why)} |"
        )
    lines += [
        "",
        f"Budget saved: {saved.describe()} (the summed budgets of its job dirs): over the jobs "
        "stopped early, their budget less the steps they reached.",
    ]
    unknown = [j for j in early if j.budget is None]
    if unknown:
        lines.append(
            f"{len(unknown)} job(s) stopped early have no readable budget (config.yaml): "
            "not counted."
        )
    return lines


def threshold_markdown(stats: list[ConfigStats]) -> list[str]:
    """The steps-to-threshold section: per configuration, how many seeds with a result reached the
    threshold (k/n) and the median and IQM of their steps to it, once and IN_A_ROW in a row."""
    t = stats[0].threshold.threshold
    lines = [
        f"## Steps to threshold: `{t.metric}` >= {t.value:.15g}",
        "",
        f"Per finished (or stopped early) seed, in step order of its logged `{t.metric}` values: "
        f"**first**, the step of the first value at or above {t.value:.15g}; **{IN_A_ROW} in a "
        f"row**, the step of the first of the first {IN_A_ROW} consecutive values at or above it. "
        "Reached k/n: k of the n seeds reached it; median and IQM are over those k only (n/a when "
        "none did).",
        "",
        f"| configuration | reached | median step | IQM step | reached ({IN_A_ROW} in a row) "
        f"| median step ({IN_A_ROW} in a row) | IQM step ({IN_A_ROW} in a row) |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in stats:
        cells = [f"`{s.label}`"]
        for steps in (s.threshold.first, s.threshold.in_a_row):
            k, median, iqm_ = reached_stats(steps)
            cells += [f"{k}/{s.threshold.n}", _fmt(median, 0), _fmt(iqm_, 0)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def optuna_markdown(sweep_dir: Path) -> list[str]:
    """The trials of an Optuna sweep's study (``<sweep dir>/optuna.db``, rlexp's resumable
    sweeper): number, job dir, state, value and parameters; [] when the sweep dir has no study."""
    if not (sweep_dir / OPTUNA_STUDY).is_file():
        return []
    try:
        from rlexp.launch.optuna_sweeper import read_trials
    except ImportError as exc:  # no rlexp[optuna] where the report runs
        return ["", "## Optuna trials", "", f"`{OPTUNA_STUDY}` not read: {_first_line(exc)}."]
    trials = read_trials(sweep_dir)
    if isinstance(trials, str):
        return ["", "## Optuna trials", "", f"`{OPTUNA_STUDY}` not read: {trials}."]
    lines: list[str] = []
    for name in dict.fromkeys(t["study"] for t in trials):
        mine = [t for t in trials if t["study"] == name]
        params = list(dict.fromkeys(k for t in mine for k in t["params"]))
        n_done = sum(t["state"] == "COMPLETE" for t in mine)
        lines += [
            "",
            f"## Optuna trials (study `{name}`: {len(mine)} trials, {n_done} complete)",
            "",
            f"From `{OPTUNA_STUDY}`, in trial order. Job: the trial's dir; a failed trial is retried "
            "with its parameters in its own dir (`retry of`: the trial it repeats).",
            "",
            "| trial | job | state | value | "
            + " | ".join(f"`{p}`" for p in params)
            + " | retry of |",
            "|---|---|---|---|" + "---|" * len(params) + "---|",
        ]
        for t in mine:
            value = ", ".join(_fmt(v) for v in t["values"]) if t["values"] else "n/a"
            cells = [
                str(t["number"]),
                f"`{t['job']}`" if t["job"] is not None else "n/a",
                t["state"],
                value,
                *(
                    f"{t['params'][p]:.6g}"
                    if isinstance(t["params"].get(p), float)
                    else _cell(t["params"].get(p, ""))
                    for p in params
                ),
                str(t["retry_of"]) if t["retry_of"] is not None else "",
            ]
            lines.append("| " + " | ".join(cells) + " |")
    return lines


#: Steps bootstrapped in one call in ``curve_band`` (memory: rows x 5000 resamples x seeds).
BAND_ROWS = 200


def curve_band(ys: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per step (a column of ``ys``: seeds x steps, NaN where a seed has no value there): the IQM
    over the seeds that have a value and its 95% percentile-bootstrap interval, computed as the
    table's (``iqm``, ``bootstrap_ci``: same resamples, same seed), so the band at a step is the
    interval the table gives for those values. A percentile interval of the IQM never leaves the
    values' range; with one seed, or all seeds equal, the band is that value."""
    from scipy.stats import bootstrap

    n_steps = ys.shape[1]
    center, low, high = (np.full(n_steps, np.nan) for _ in range(3))
    have = ~np.isnan(ys)
    by_seeds: dict[bytes, list[int]] = {}  # steps that the same seeds logged: one bootstrap
    for j in range(n_steps):
        by_seeds.setdefault(have[:, j].tobytes(), []).append(j)
    for cols in map(np.array, by_seeds.values()):
        x = ys[have[:, cols[0]]][:, cols].T  # steps x seeds
        if x.shape[1] == 0:
            continue
        center[cols] = iqm(x, axis=-1)
        low[cols] = high[cols] = x[:, 0]
        spread = (x.shape[1] > 1) & ~np.all(x == x[:, :1], axis=1)
        for start in range(0, int(spread.sum()), BAND_ROWS):
            rows = np.flatnonzero(spread)[start : start + BAND_ROWS]
            res = bootstrap(
                (x[rows],),
                iqm,
                confidence_level=0.95,
                n_resamples=5000,
                method="percentile",
                vectorized=True,
                axis=-1,
                random_state=np.random.default_rng(seed),
            )
            low[cols[rows]] = res.confidence_interval.low
            high[cols[rows]] = res.confidence_interval.high
    return center, low, high


def plot_curves(
    stats: list[ConfigStats], path: Path, metric: str, threshold: float | None = None
) -> None:
    """IQM learning curve per configuration with its 95% bootstrap band over seeds: the statistic
    of the table (``curve_band``), so the band at the last step is the table's IQM interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    for s in stats:
        # A seed stopped early ends its curve at the stop: past it, the band is over the others.
        curves = [j.curve for j in s.jobs if j.result and j.curve]
        if not curves:
            continue
        early = sum(j.stopped_early for j in s.jobs if j.result and j.curve)
        steps = np.array(sorted({step for c in curves for step, _ in c}), dtype=float)
        # Seeds evaluate at the same steps unless configs differ; interpolate inside each seed's range.
        ys = np.full((len(curves), len(steps)), np.nan)
        for i, c in enumerate(curves):
            cs, cv = np.array(c, dtype=float).T
            inside = (steps >= cs[0]) & (steps <= cs[-1])
            ys[i, inside] = np.interp(steps[inside], cs, cv)
        center, low, high = curve_band(ys)
        stopped = f", {early} stopped early" if early else ""
        (line,) = ax.plot(steps, center, label=f"{s.label} (n={len(curves)}{stopped})")
        ax.fill_between(steps, low, high, alpha=0.2, color=line.get_color())
    if threshold is not None:
        ax.axhline(
            threshold,
            color="gray",
            linestyle="--",
            linewidth=1,
            label=f"threshold {threshold:.15g}",
        )
    ax.set_xlabel("env steps")
    ax.set_ylabel(metric)
    ax.set_title("IQM over seeds, 95% percentile bootstrap CI (as in report.md)")
    ax.grid(alpha=0.3)
    if ax.lines:
        ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(
    sweep_dir: Path,
    metric: str = DEFAULT_METRIC,
    plot: bool = True,
    threshold: float | None = None,
    threshold_metric: str | None = None,
) -> str:
    """Write report.md, report.csv (and curves.png) into ``sweep_dir``; return the markdown. What
    cannot be written (a read-only sweep dir) is said in one warning; the markdown is returned.
    ``threshold``: also the steps each seed took to reach it in ``threshold_metric`` (default:
    ``metric``)."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise FileNotFoundError(f"no sweep dir {sweep_dir}")
    target = Threshold(threshold_metric or metric, threshold) if threshold is not None else None
    sweep = read_sweep(sweep_dir, metric, other_metrics=(target.metric,) if target else ())
    if not sweep.jobs and sweep.plan.jobs is None:
        raise FileNotFoundError(
            f"no jobs under {sweep_dir} (no */.hydra/overrides.yaml) and no multirun.yaml: "
            "is it a multirun dir?"
        )
    stats = summarize(sweep.jobs, target)
    md = to_markdown(sweep_dir, sweep, stats, metric)
    trials = optuna_markdown(sweep_dir)  # an Optuna sweep: its study's trials
    if trials:
        md += "\n".join(trials) + "\n"
    outputs = {"report.md": lambda p: p.write_text(md)}
    outputs["report.csv"] = lambda p: p.write_text(to_csv(stats))
    if plot:
        line = target.value if target and target.metric == metric else None
        outputs["curves.png"] = lambda p: plot_curves(stats, p, metric, line)
    written, failed = [], []
    for name, write in outputs.items():
        try:
            write(sweep_dir / name)
            written.append(name)
        except OSError as exc:
            failed.append((name, exc.strerror or _first_line(exc)))
    if written:
        log.info("wrote %s into %s", ", ".join(written), sweep_dir)
    if failed:
        names = ", ".join(name for name, _ in failed)
        log.warning("rlexp report: could not write %s into %s (%s)", names, sweep_dir, failed[0][1])
    return md
