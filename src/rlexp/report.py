"""``rlexp report SWEEP_DIR``: per-configuration statistics and learning curves of a Hydra sweep.

A configuration is a job's overrides (``.hydra/overrides.yaml``) less the seed; its seeds are the
jobs that share it. For each configuration: the final eval return over seeds (mean +- std, and the
interquartile mean with a 95% bootstrap confidence interval, as rliable recommends for few seeds),
steps and training time. Jobs whose ``status.json`` is missing or not ``finished`` are listed apart,
never silently dropped. Writes ``report.md``, ``report.csv`` and ``curves.png`` into the sweep dir.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

log = logging.getLogger(__name__)

#: The metric whose last value is a job's final score, and whose history is its learning curve.
DEFAULT_METRIC = "eval/episode_return"
#: Override keys that name a seed rather than a configuration.
SEED_KEYS = ("seed",)
#: Time inside the training loop per iteration (summed: requeue waits and startup don't count).
TIME_KEYS = ("perf/collect_time", "perf/update_time", "perf/eval_time")


@dataclass
class Job:
    """One job of the sweep: its dir, overrides, status and metric history."""

    path: Path
    overrides: list[str]
    seed: str | None
    state: str  # finished | running | stopped | interrupted | failed | missing
    global_step: int
    reason: str = ""
    curve: list[tuple[int, float]] = field(default_factory=list)  # (step, metric), one per step
    time_s: float = 0.0

    @property
    def final(self) -> float | None:
        """The metric's last logged value (the job's final eval), or None when it never evaluated."""
        return self.curve[-1][1] if self.curve else None

    @property
    def finished(self) -> bool:
        return self.state == "finished" and self.final is not None


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

    @property
    def n_unfinished(self) -> int:
        return sum(not j.finished for j in self.jobs)


def _split(override: str) -> tuple[str, str]:
    key, _, value = override.partition("=")
    return key.lstrip("+~"), value


def read_metrics(path: Path, metric: str) -> tuple[list[tuple[int, float]], float]:
    """``metrics.jsonl`` -> the metric's history (last row per step wins: a resumed attempt may
    re-log steps after its checkpoint) and the summed training-loop time."""
    values: dict[int, float] = {}
    times: dict[int, float] = {}
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return [], 0.0
    for line in lines:
        try:
            row = json.loads(line)
        except ValueError:
            continue  # a line cut short by a kill
        step = int(row.get("step", -1))
        if metric in row and row[metric] is not None and math.isfinite(row[metric]):
            values[step] = float(row[metric])
        if any(k in row for k in TIME_KEYS):
            times[step] = sum(float(row.get(k, 0.0)) for k in TIME_KEYS)
    return sorted(values.items()), float(sum(times.values()))


def find_jobs(sweep_dir: Path, metric: str = DEFAULT_METRIC) -> list[Job]:
    """Every job dir under ``sweep_dir`` (one with ``.hydra/overrides.yaml``), in job-number order."""
    jobs = []
    for ov_file in sweep_dir.rglob(".hydra/overrides.yaml"):
        job_dir = ov_file.parent.parent
        if ".submitit" in job_dir.parts:
            continue
        overrides = [str(o) for o in (OmegaConf.to_container(OmegaConf.load(ov_file)) or [])]
        seed = next((v for k, v in map(_split, overrides) if k in SEED_KEYS), None)
        try:
            status = json.loads((job_dir / "status.json").read_text())
        except (OSError, ValueError):
            status = {}
        curve, time_s = read_metrics(job_dir / "metrics.jsonl", metric)
        jobs.append(
            Job(
                path=job_dir,
                overrides=overrides,
                seed=seed,
                state=str(status.get("state", "missing")),
                global_step=int(status.get("global_step", curve[-1][0] if curve else 0)),
                reason=str(status.get("reason", "")),
                curve=curve,
                time_s=time_s,
            )
        )

    def order(job: Job) -> tuple:
        rel = job.path.relative_to(sweep_dir).parts
        return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in rel)

    return sorted(jobs, key=order)


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


def summarize(jobs: list[Job]) -> list[ConfigStats]:
    """Group jobs by configuration and compute the statistics over finished seeds."""
    common = set(common_overrides(jobs))
    groups: dict[tuple[str, ...], list[Job]] = {}
    for job in jobs:
        groups.setdefault(config_key(job), []).append(job)
    stats = []
    for key, members in groups.items():
        done = [j for j in members if j.finished]
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
            )
        )
    return stats


def _fmt(x: float, digits: int = 2) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


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
]


def to_csv(stats: list[ConfigStats]) -> str:
    """One row per configuration."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_FIELDS, lineterminator="\n")
    writer.writeheader()
    for s in stats:
        writer.writerow(
            {
                "configuration": s.label,
                "n_seeds": len(s.finals),
                "seeds": " ".join(str(j.seed) for j in s.jobs if j.finished),
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
            }
        )
    return buf.getvalue()


def to_markdown(sweep_dir: Path, jobs: list[Job], stats: list[ConfigStats], metric: str) -> str:
    """The human-readable report: one table of configurations, one of unfinished jobs."""
    n_done = sum(j.finished for j in jobs)
    lines = [
        f"# Sweep report: `{sweep_dir}`",
        "",
        f"{len(jobs)} jobs, {n_done} finished, {len(stats)} configuration(s). Score: the last "
        f"`{metric}` of each finished job. IQM: interquartile mean; CI: 95% percentile bootstrap "
        "over seeds. Time: seconds inside the training loop (collect + update + eval).",
        "",
    ]
    common = common_overrides(jobs)
    if common:
        lines += ["Shared overrides: `" + " ".join(common) + "`", ""]
    lines += [
        "| configuration | seeds | final mean ± std | IQM [95% CI] | steps | time (s) | unfinished |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in sorted(stats, key=lambda s: -s.iqm if not math.isnan(s.iqm) else math.inf):
        lines.append(
            f"| `{s.label}` | {len(s.finals)} | {_fmt(s.mean)} ± {_fmt(s.std)} | {_fmt(s.iqm)} "
            f"[{_fmt(s.iqm_ci[0])}, {_fmt(s.iqm_ci[1])}] | {_fmt(s.steps, 0)} | {_fmt(s.time_s, 1)} "
            f"| {s.n_unfinished} |"
        )
    bad = [j for j in jobs if not j.finished]
    lines += ["", f"## Unfinished or failed jobs ({len(bad)})", ""]
    if bad:
        lines += ["| job | overrides | state | step | reason |", "|---|---|---|---|---|"]
        for j in bad:
            state = j.state if j.state != "finished" else f"finished, no `{metric}` logged"
            lines.append(
                f"| `{j.path.relative_to(sweep_dir)}` | `{' '.join(j.overrides)}` | {state} "
                f"| {j.global_step} | {j.reason} |"
            )
    else:
        lines.append("None.")
    return "\n".join(lines) + "\n"


def plot_curves(stats: list[ConfigStats], path: Path, metric: str) -> None:
    """Mean learning curve per configuration with a 95% t-interval band over seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.stats import t as student_t

    fig, ax = plt.subplots(figsize=(8, 5))
    for s in stats:
        curves = [j.curve for j in s.jobs if j.finished and j.curve]
        if not curves:
            continue
        steps = np.array(sorted({step for c in curves for step, _ in c}), dtype=float)
        # Seeds evaluate at the same steps unless configs differ; interpolate inside each seed's range.
        ys = np.full((len(curves), len(steps)), np.nan)
        for i, c in enumerate(curves):
            cs, cv = np.array(c, dtype=float).T
            inside = (steps >= cs[0]) & (steps <= cs[-1])
            ys[i, inside] = np.interp(steps[inside], cs, cv)
        n = np.sum(~np.isnan(ys), axis=0)
        mean = np.nanmean(ys, axis=0)
        std = np.nanstd(ys, axis=0, ddof=1) if len(curves) > 1 else np.zeros_like(mean)
        half = np.where(n > 1, student_t.ppf(0.975, np.maximum(n - 1, 1)) * std / np.sqrt(n), 0.0)
        (line,) = ax.plot(steps, mean, label=f"{s.label} (n={len(curves)})")
        ax.fill_between(steps, mean - half, mean + half, alpha=0.2, color=line.get_color())
    ax.set_xlabel("env steps")
    ax.set_ylabel(metric)
    ax.set_title("mean over seeds, 95% CI")
    ax.grid(alpha=0.3)
    if ax.lines:
        ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(sweep_dir: Path, metric: str = DEFAULT_METRIC, plot: bool = True) -> str:
    """Write report.md, report.csv (and curves.png) into ``sweep_dir``; return the markdown."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise FileNotFoundError(f"no sweep dir {sweep_dir}")
    jobs = find_jobs(sweep_dir, metric)
    if not jobs:
        raise FileNotFoundError(
            f"no jobs under {sweep_dir} (no */.hydra/overrides.yaml): is it a multirun dir?"
        )
    stats = summarize(jobs)
    md = to_markdown(sweep_dir, jobs, stats, metric)
    (sweep_dir / "report.md").write_text(md)
    (sweep_dir / "report.csv").write_text(to_csv(stats))
    if plot:
        plot_curves(stats, sweep_dir / "curves.png", metric)
    log.info("wrote %s, report.csv%s", sweep_dir / "report.md", ", curves.png" if plot else "")
    return md
