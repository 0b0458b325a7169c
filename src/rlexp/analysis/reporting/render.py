"""``report.md`` and ``report.csv``: the configurations ranked by IQM, steps to a threshold, jobs
stopped early and the budget they saved, failed or unfinished jobs, jobs that never started, and
the files that could only be read in part."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rlexp.analysis.reporting.jobs import Job
from rlexp.analysis.reporting.plan import Sweep
from rlexp.analysis.reporting.summary import (
    ConfigStats,
    ThresholdStats,
    budget_saved,
    common_overrides,
)
from rlexp.analysis.stats import IN_A_ROW, reached_stats
from rlexp.common.table import fixed, markdown_cell

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


def to_markdown(
    sweep_dir: Path,
    sweep: Sweep,
    stats: list[ConfigStats],
    metric: str,
    after_table: Sequence[str] = (),
) -> str:
    """The human-readable report: configurations, jobs stopped early and the budget they saved,
    failed or unfinished jobs, jobs that never started, and the files that could only be read in
    part. ``after_table``: lines of a section placed right after the configurations table (the
    results per env)."""
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
            f"| `{s.label}` | {len(s.finals)} | {fixed(s.mean)} ± {fixed(s.std)} | {fixed(s.iqm)} "
            f"[{fixed(s.iqm_ci[0])}, {fixed(s.iqm_ci[1])}] | {fixed(s.steps, 0)} | {fixed(s.time_s, 1)} "
            f"| {s.n_unfinished} |" + (f" {s.n_stopped_early} |" if early else "")
        )
    if after_table:
        lines += ["", *after_table]
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
                f"| {j.global_step} | {markdown_cell(reason)} |"
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
        final = fixed(j.final) if j.final is not None else "n/a"
        lines.append(
            f"| `{j.path.relative_to(sweep_dir)}` | `{' '.join(j.overrides)}` | {j.global_step} "
            f"| {budget} | {final} | {markdown_cell(j.why)} |"
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
            cells += [f"{k}/{s.threshold.n}", fixed(median, 0), fixed(iqm_, 0)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines
