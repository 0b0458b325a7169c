"""Results per env (``rlexp report`` on a sweep over envs, e.g. ``+sweep=mujoco_1m``): per
configuration of the sweep, its env's two result metrics over seeds (the mean return of the last
100 training episodes at the end of training, and the final deterministic evaluation's mean return),
each as IQM with a 95% bootstrap interval and as mean ± std, next to the published anchors that
measure the same thing (``rlexp.analysis.reporting.anchors``), the eval success rate for tasks that define
success, the median wall time per job and the env steps per second, and the time to the CleanRL
mean and to the rl-zoo mean (``TimeTo``: the env steps and wall-clock until the training return,
respectively the deterministic eval return, first reached it).
Written as a section of ``report.md`` and as ``results.csv``; the curves are
``rlexp.analysis.reporting.plot.plot_results``."""

from __future__ import annotations

import csv
import io
import math
import statistics
from dataclasses import dataclass

import numpy as np

from rlexp.analysis.reporting.anchors import (
    CLEANRL,
    EVAL,
    RL_ZOO,
    SOURCES,
    TRAIN,
    Anchor,
    Source,
    anchors_for,
)
from rlexp.analysis.reporting.jobs import STOPPED_EARLY, Job, split_override
from rlexp.analysis.reporting.summary import common_overrides, config_key
from rlexp.analysis.stats import bootstrap_ci, iqm, steps_to_threshold
from rlexp.common.table import fixed, format_duration

#: The mean return of the last 100 training episodes, as the trainer logs it every iteration.
TRAIN_METRIC = "train/episode_return"
#: The mean return of an evaluation of the deterministic policy (every ``trainer.eval_every``).
EVAL_METRIC = "eval/episode_return"
#: The share of evaluation episodes that succeeded: only meaningful for tasks that define success.
SUCCESS_METRIC = "eval/success_rate"
#: The metrics the results view reads from each job's ``metrics.jsonl``.
RESULT_METRICS = (TRAIN_METRIC, EVAL_METRIC, SUCCESS_METRIC)
#: Env backends whose tasks have no success signal: Gymnasium's tasks (MuJoCo among them) define
#: none, and the evaluation's ``eval/success_rate`` is a constant 0 for them, so it is not shown.
NO_SUCCESS_BACKENDS = ("gymnasium", "gymnasium_async", "envpool")


def env_of(job: Job) -> str | None:
    """The job's env: its config's ``env.name``, else its ``env=`` override (no readable config)."""
    if job.env:
        return job.env
    return next((v for k, v in map(split_override, job.overrides) if k == "env"), None)


def varies_env(jobs: list[Job]) -> bool:
    """Whether the sweep's jobs train on more than one env (the results view is then automatic)."""
    return len({env_of(j) for j in jobs} - {None}) > 1


def defines_success(backend: str | None) -> bool:
    """Whether a task of this env backend reports success (rlexp's native tasks do)."""
    return backend is not None and backend not in NO_SUCCESS_BACKENDS


@dataclass(frozen=True)
class OverSeeds:
    """One metric's final values over the seeds that logged it, and their statistics."""

    values: np.ndarray
    iqm: float
    iqm_ci: tuple[float, float]
    mean: float
    std: float  # ddof 1, as the report's main table; NaN with one seed

    @property
    def n(self) -> int:
        return len(self.values)


def over_seeds(values: list[float]) -> OverSeeds:
    """IQM with its 95% percentile bootstrap interval (``rlexp.analysis.stats``), mean and std."""
    x = np.asarray(values, dtype=float)
    if not len(x):
        return OverSeeds(x, math.nan, (math.nan, math.nan), math.nan, math.nan)
    std = float(x.std(ddof=1)) if len(x) > 1 else math.nan
    return OverSeeds(x, float(iqm(x)), bootstrap_ci(x, iqm), float(x.mean()), std)


@dataclass
class EnvResult:
    """One configuration of a sweep over envs: its env, its seeds' results and the anchors."""

    env: str  # env.name, e.g. Hopper-v5
    label: str  # the configuration less the env and what all jobs share ("" when only env varies)
    jobs: list[Job]  # its jobs with a result: finished or stopped early
    n_jobs: int  # all its job dirs
    train: OverSeeds
    eval: OverSeeds
    success: OverSeeds | None  # None: the task defines no success
    wall_s: float  # median over its jobs with a result
    steps_per_s: float  # median over them of global_step / wall
    anchors: dict[str, Anchor]  # by Source.key
    to_cleanrl: TimeTo | None = None  # None: no CleanRL anchor for the env
    to_rl_zoo: TimeTo | None = None  # None: no rl-zoo anchor for the env

    def time_to(self, source: Source) -> TimeTo | None:
        """The time to ``source``'s number (CleanRL's or rl-zoo's); None without one."""
        return {CLEANRL.key: self.to_cleanrl, RL_ZOO.key: self.to_rl_zoo}.get(source.key)

    @property
    def n(self) -> int:
        return len(self.jobs)


@dataclass(frozen=True)
class TimeTo:
    """Time to result: per seed the first logged value of the anchor's metric (the train return
    for CleanRL, the deterministic eval return for rl-zoo) >= the anchor's mean, its env step and
    its wall-clock (the row's ``time`` less the job's start, ``provenance.json``)."""

    target: float  # the anchor's mean
    n: int  # the seeds with a result (the row's seeds)
    steps: list[int]  # one per seed that reached the target: the step of its first row >= target
    seconds: list[float]  # of those seeds, the ones whose row has a time since a one-attempt start

    @property
    def k(self) -> int:
        """How many seeds reached the target."""
        return len(self.steps)

    @property
    def median_steps(self) -> float:
        return _median(self.steps)

    @property
    def median_s(self) -> float:
        return _median(self.seconds)


def time_to(jobs: list[Job], target: float, metric: str = TRAIN_METRIC) -> TimeTo:
    """Per job, the first step whose ``metric`` is >= ``target`` (``rlexp.analysis.stats.steps_to_threshold``,
    one value) and the seconds from the job's start to the row that logged it. No seconds for a
    job resumed (a row written before its start: the start is its last attempt's) nor for a row
    with no ``time``."""
    steps, seconds = [], []
    for job in jobs:
        step = steps_to_threshold(job.curves.get(metric) or [], target)
        if step is None:
            continue
        steps.append(step)
        times = job.logged_at.get(metric, {})
        one_attempt = job.start is not None and all(t >= job.start for t in times.values())
        if one_attempt and step in times:
            seconds.append(times[step] - job.start)
    return TimeTo(target, len(jobs), steps, seconds)


def _last(job: Job, metric: str) -> float | None:
    curve = job.curves.get(metric) or []
    return curve[-1][1] if curve else None


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else math.nan


def env_results(jobs: list[Job]) -> list[EnvResult]:
    """One EnvResult per configuration (its overrides less the seed), in job order; each job's
    ``curves`` must hold RESULT_METRICS (``rlexp.analysis.reporting.jobs.add_histories``)."""
    common = set(common_overrides(jobs))
    groups: dict[tuple[str, ...], list[Job]] = {}
    for job in jobs:
        groups.setdefault(config_key(job), []).append(job)
    out = []
    for key, members in groups.items():
        done = [j for j in members if j.state in ("finished", STOPPED_EARLY)]
        envs = list(dict.fromkeys(e for e in map(env_of, members) if e))
        env = " / ".join(envs) or "(unknown env)"
        # Shown where the jobs logged it (rlexp logs it for tasks that define success) and their
        # backend can define it (runs of older rlexp logged a constant 0 for Gymnasium tasks).
        backends = {j.backend for j in members if j.backend}
        success = any(map(defines_success, backends)) and any(
            _last(j, SUCCESS_METRIC) is not None for j in done
        )
        walls = [j.wall_s for j in done if j.wall_s]
        anchors = anchors_for(envs[0] if len(envs) == 1 else None)
        cleanrl, rl_zoo = anchors.get(CLEANRL.key), anchors.get(RL_ZOO.key)

        def finals(metric: str, done: list[Job] = done) -> OverSeeds:
            return over_seeds([v for v in (_last(j, metric) for j in done) if v is not None])

        out.append(
            EnvResult(
                env=env,
                label=" ".join(o for o in key if o not in common and split_override(o)[0] != "env"),
                jobs=done,
                n_jobs=len(members),
                train=finals(TRAIN_METRIC),
                eval=finals(EVAL_METRIC),
                success=finals(SUCCESS_METRIC) if success else None,
                wall_s=_median(walls),
                steps_per_s=_median([j.global_step / j.wall_s for j in done if j.wall_s]),
                anchors=anchors,
                to_cleanrl=time_to(done, cleanrl.mean) if cleanrl is not None else None,
                to_rl_zoo=time_to(done, rl_zoo.mean, EVAL_METRIC) if rl_zoo is not None else None,
            )
        )
    return out


def _used_sources(results: list[EnvResult]) -> list[Source]:
    """The anchor sources with a number for at least one of the envs (the others get no column)."""
    return [s for s in SOURCES if any(s.key in r.anchors for r in results)]


def _iqm_cell(s: OverSeeds, n: int, digits: int = 0) -> str:
    """``IQM [low, high]``, and how many seeds logged it when not all of the row's did."""
    if not s.n:
        return "n/a"
    cell = f"{fixed(s.iqm, digits)} [{fixed(s.iqm_ci[0], digits)}, {fixed(s.iqm_ci[1], digits)}]"
    return cell + (f" ({s.n} of {n} seeds)" if s.n < n else "")


def _mean_cell(s: OverSeeds) -> str:
    return "n/a" if not s.n else f"{fixed(s.mean, 0)} ± {fixed(s.std, 0)}"


def _anchor_cell(a: Anchor | None) -> str:
    if a is None:
        return ""
    if a.ci is not None:  # an IQM over seeds: its interval, as our own cells
        return f"{fixed(a.mean, 0)} [{fixed(a.ci[0], 0)}, {fixed(a.ci[1], 0)}] ({a.env_id})"
    return f"{fixed(a.mean, 0)} ± {fixed(a.std, 0)} ({a.env_id})"


def _steps(x: float) -> str:
    """Env steps in three digits: ``950``, ``5.5k``, ``412k``, ``1M``."""
    if x < 1000:
        return f"{x:.0f}"
    return f"{x / 1e3:.3g}k" if x < 999_500 else f"{x / 1e6:.3g}M"


def _time_to_cells(t: TimeTo | None) -> list[str]:
    """``412k (5/5)`` and ``3m51s``: the medians over the seeds that reached the target; ``—``
    with no anchor; ``not reached (0/5)``; the time over fewer seeds says how many."""
    if t is None:
        return ["—", "—"]
    if not t.k:
        return [f"not reached (0/{t.n})", "—"]
    wall = format_duration(t.median_s) if t.seconds else "n/a"
    wall += f" ({len(t.seconds)} of {t.k} seeds)" if 0 < len(t.seconds) < t.k else ""
    return [f"{_steps(t.median_steps)} ({t.k}/{t.n})", wall]


def results_markdown(results: list[EnvResult]) -> list[str]:
    """The section ``## Results per env`` of report.md: the table, then what each column is and
    where each anchor comes from."""
    sources = _used_sources(results)
    by_metric = {m: [s for s in sources if s.measures == m] for m in (TRAIN, EVAL)}
    with_label = any(r.label for r in results)
    with_success = any(r.success is not None for r in results)
    head = ["env"] + (["configuration"] if with_label else []) + ["seeds"]
    head += ["train return: IQM [95% CI]", "train mean ± std"]
    head += [f"{s.name} ({i})" for i, s in enumerate(sources, 1) if s.measures == TRAIN]
    head += ["eval return: IQM [95% CI]", "eval mean ± std"]
    head += [f"{s.name} ({i})" for i, s in enumerate(sources, 1) if s.measures == EVAL]
    head += ["eval success: IQM [95% CI]"] if with_success else []
    head += ["wall per job (median)", "env steps/s (median)"]
    timed = [s for s in sources if s.time_to]  # CleanRL's (train return), rl-zoo's (eval return)
    for s in timed:
        which = "" if s.measures == TRAIN else "eval "
        head += [
            f"steps to {s.short} {which}mean (median, seeds)",
            f"wall to {s.short} mean (median)",
        ]
    with_time_to = CLEANRL in timed
    lines = [
        "## Results per env",
        "",
        "Per env (each configuration of the sweep), over its seeds that finished or were stopped "
        f"early. **Train return**: the last logged `{TRAIN_METRIC}`, the mean return of the last "
        "100 training episodes (stochastic policy) at the end of training. **Eval return**: the "
        f"last `{EVAL_METRIC}`, the mean return of the final evaluation of the deterministic "
        "policy (`trainer.eval_episodes` episodes). IQM with its 95% percentile bootstrap interval "
        "over seeds, as above; std with ddof 1. **Wall**: per job, from its start "
        "(`provenance.json`, written once its envs are built) to its end (`status.json`): "
        "training, evaluations and checkpoints (a resumed job: its last attempt); **env steps/s**: "
        "the median over jobs of their steps / wall."
        + (
            f" **To CleanRL mean**: per seed, the first logged `{TRAIN_METRIC}` >= the CleanRL "
            "anchor's mean: its env step, and its row's `time` less the job's start "
            "(`provenance.json`); the median over the seeds that reached it, (k/n): how many did. "
            "A resumed job's steps count, its time does not (its start is its last attempt's)."
            if with_time_to
            else ""
        )
        + (
            f" **To rl-zoo mean**: the same with the deterministic eval return (`{EVAL_METRIC}`, "
            "every `trainer.eval_every` steps) and the rl-zoo anchor's mean, which measures it."
            if RL_ZOO in timed
            else ""
        ),
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for r in results:
        cells = [f"`{r.env}`"] + ([f"`{r.label}`" if r.label else ""] if with_label else [])
        cells.append(f"{r.n}" + (f" of {r.n_jobs}" if r.n < r.n_jobs else ""))
        cells += [_iqm_cell(r.train, r.n), _mean_cell(r.train)]
        cells += [_anchor_cell(r.anchors.get(s.key)) for s in by_metric[TRAIN]]
        cells += [_iqm_cell(r.eval, r.n), _mean_cell(r.eval)]
        cells += [_anchor_cell(r.anchors.get(s.key)) for s in by_metric[EVAL]]
        if with_success:
            cells.append(_iqm_cell(r.success, r.n, 2) if r.success is not None else "—")
        wall = format_duration(r.wall_s) if not math.isnan(r.wall_s) else "n/a"
        cells += [wall, fixed(r.steps_per_s, 0)]
        for s in timed:
            cells += _time_to_cells(r.time_to(s))
        lines.append("| " + " | ".join(cells) + " |")
    if with_success:
        lines += [
            "",
            "Eval success only for tasks that define success (rlexp's native tasks); "
            "Gymnasium's tasks have none (—).",
        ]
    if sources:
        lines += [
            "",
            "Anchors: numbers from elsewhere (published ones; rlexp defaults: rlexp's own recorded "
            "results), not runs of this sweep, next to the metric they "
            "measure; an empty cell: the source has no number for that task. They ran other "
            "versions of the tasks (the env id in each cell) with their own hyperparameters: "
            "reference points, not like-for-like comparisons.",
            "",
        ]
        lines += [
            f"{i}. **{s.name}**: {s.what}. Source: {s.where}." for i, s in enumerate(sources, 1)
        ]
    return lines


def results_csv(results: list[EnvResult]) -> str:
    """``results.csv``: one row per env (configuration), every number of the section."""
    sources = _used_sources(results)
    fields = ["env", "configuration", "n_seeds", "n_jobs", "seeds"]
    for m in ("train", "eval", "success"):
        fields += [f"{m}_{k}" for k in ("n", "iqm", "iqm_ci_low", "iqm_ci_high", "mean", "std")]
    fields += ["wall_median_s", "env_steps_per_s_median"]
    for s in sources:
        fields += [f"{s.key}_env", f"{s.key}_mean", f"{s.key}_std"]
        if not s.time_to:  # rlexp's own results: an IQM and its interval
            fields += [f"{s.key}_ci_low", f"{s.key}_ci_high"]
    timed = [s for s in sources if s.time_to]
    for s in timed:  # time to its mean: empty for an env with no number of that source
        fields += [f"{s.key}_{k}" for k in ("reached", "steps_median", "wall_median_s", "wall_n")]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for r in results:
        row = {
            "env": r.env,
            "configuration": r.label,
            "n_seeds": r.n,
            "n_jobs": r.n_jobs,
            "seeds": " ".join(str(j.seed) for j in r.jobs),
            "wall_median_s": r.wall_s,
            "env_steps_per_s_median": r.steps_per_s,
        }
        for m, s in (("train", r.train), ("eval", r.eval), ("success", r.success)):
            if s is not None:  # success: empty cells for a task that defines none
                row.update(
                    {
                        f"{m}_n": s.n,
                        f"{m}_iqm": s.iqm,
                        f"{m}_iqm_ci_low": s.iqm_ci[0],
                        f"{m}_iqm_ci_high": s.iqm_ci[1],
                        f"{m}_mean": s.mean,
                        f"{m}_std": s.std,
                    }
                )
        for s in sources:
            a = r.anchors.get(s.key)
            if a is not None:
                row.update({f"{s.key}_env": a.env_id, f"{s.key}_mean": a.mean})
                row[f"{s.key}_std"] = a.std if a.ci is None else ""
                if a.ci is not None:
                    row.update({f"{s.key}_ci_low": a.ci[0], f"{s.key}_ci_high": a.ci[1]})
        for s in timed:
            t = r.time_to(s)
            if t is None:
                continue
            row[f"{s.key}_reached"] = t.k
            row[f"{s.key}_wall_n"] = len(t.seconds)
            if t.k:
                row[f"{s.key}_steps_median"] = t.median_steps
            if t.seconds:
                row[f"{s.key}_wall_median_s"] = t.median_s
        writer.writerow(row)
    return buf.getvalue()
