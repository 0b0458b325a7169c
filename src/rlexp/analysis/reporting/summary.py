"""Statistics per configuration of a sweep (its jobs' overrides less the seed): the final values
over seeds, steps to a threshold, and the budget that early stops saved."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from rlexp.analysis.reporting.jobs import SEED_KEYS, Job, split_override
from rlexp.analysis.stats import IN_A_ROW, bootstrap_ci, iqm, steps_to_threshold
from rlexp.common.table import fixed


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
        text = f"{self.saved} env steps, {fixed(100 * self.share, 1)}% of the sweep's {self.total}"
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


def config_key(job: Job) -> tuple[str, ...]:
    """A job's configuration: its overrides without the seed."""
    return tuple(o for o in job.overrides if split_override(o)[0] not in SEED_KEYS)


def common_overrides(jobs: list[Job]) -> list[str]:
    """Overrides every job shares (shown once, not in every configuration's label)."""
    keys = [set(config_key(j)) for j in jobs]
    common = set.intersection(*keys) if keys else set()
    return [o for o in config_key(jobs[0]) if o in common] if jobs else []


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
