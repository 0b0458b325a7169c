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
the report is still returned. A sweep over envs (or ``results=True``) also gets the results per env
(both result metrics with the published anchors, wall time, env steps/s: ``results.csv``,
``results.png``).

This module is the entry point (``report``); its parts live in ``rlexp.analysis.reporting`` (job dirs, the
plan, statistics, markdown/csv, the results per env and their anchors, Optuna trials, the plots) and
``rlexp.analysis.stats``, and are re-exported here.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from rlexp.analysis.reporting.anchors import ANCHORS, SOURCES, Anchor, Source, anchors_for
from rlexp.analysis.reporting.confirm import confirm_lines
from rlexp.analysis.reporting.jobs import (
    DEFAULT_METRIC,
    SEED_KEYS,
    STOPPED_EARLY,
    TIME_KEYS,
    Job,
    add_histories,
    find_jobs,
    first_line,
    read_budget,
    read_histories,
    read_job,
    read_metrics,
    read_overrides,
    read_status,
)
from rlexp.analysis.reporting.plan import (
    JOB_NUM_SUBDIR,
    UNEXPANDED,
    ExpectedJob,
    Plan,
    Sweep,
    match_plan,
    plan_from_config,
    read_plan,
    read_sweep,
)
from rlexp.analysis.reporting.plot import plot_curves, plot_results
from rlexp.analysis.reporting.render import (
    CSV_FIELDS,
    THRESHOLD_CSV_FIELDS,
    stopped_early_markdown,
    threshold_markdown,
    to_csv,
    to_markdown,
)
from rlexp.analysis.reporting.results import (
    RESULT_METRICS,
    EnvResult,
    env_results,
    results_csv,
    results_markdown,
    varies_env,
)
from rlexp.analysis.reporting.summary import (
    BudgetSaved,
    ConfigStats,
    Threshold,
    ThresholdStats,
    budget_saved,
    common_overrides,
    config_key,
    parse_threshold,
    summarize,
    threshold_stats,
)
from rlexp.analysis.reporting.trials import OPTUNA_STUDY, optuna_markdown
from rlexp.analysis.stats import (
    BAND_ROWS,
    IN_A_ROW,
    bootstrap_ci,
    curve_band,
    iqm,
    reached_stats,
    steps_to_threshold,
)
from rlexp.pbt.lineage import pbt_markdown, plot_schedules

#: What ``from rlexp.analysis.report import ...`` gives: the entry point and the parts it is made of.
__all__ = [
    "ANCHORS",
    "BAND_ROWS",
    "CSV_FIELDS",
    "DEFAULT_METRIC",
    "IN_A_ROW",
    "JOB_NUM_SUBDIR",
    "OPTUNA_STUDY",
    "RESULT_METRICS",
    "SEED_KEYS",
    "SOURCES",
    "STOPPED_EARLY",
    "THRESHOLD_CSV_FIELDS",
    "TIME_KEYS",
    "UNEXPANDED",
    "Anchor",
    "BudgetSaved",
    "ConfigStats",
    "EnvResult",
    "ExpectedJob",
    "Job",
    "Plan",
    "Source",
    "Sweep",
    "Threshold",
    "ThresholdStats",
    "add_histories",
    "anchors_for",
    "bootstrap_ci",
    "budget_saved",
    "common_overrides",
    "config_key",
    "curve_band",
    "env_results",
    "find_jobs",
    "iqm",
    "match_plan",
    "optuna_markdown",
    "parse_threshold",
    "plan_from_config",
    "plot_curves",
    "plot_results",
    "reached_stats",
    "read_budget",
    "read_histories",
    "read_job",
    "read_metrics",
    "read_overrides",
    "read_plan",
    "read_status",
    "read_sweep",
    "report",
    "results_csv",
    "results_markdown",
    "steps_to_threshold",
    "stopped_early_markdown",
    "summarize",
    "threshold_markdown",
    "threshold_stats",
    "to_csv",
    "to_markdown",
    "varies_env",
]

log = logging.getLogger(__name__)


def report(
    sweep_dir: Path,
    metric: str = DEFAULT_METRIC,
    plot: bool = True,
    threshold: float | None = None,
    threshold_metric: str | None = None,
    results: bool | None = None,
    results_plot: Path | None = None,
) -> str:
    """Write report.md, report.csv (and curves.png) into ``sweep_dir``; return the markdown. What
    cannot be written (a read-only sweep dir) is said in one warning; the markdown is returned.
    ``threshold``: also the steps each seed took to reach it in ``threshold_metric`` (default:
    ``metric``). ``results``: the results per env (both result metrics, anchors, wall time; also
    results.csv and results.png); None: when the sweep's jobs train on more than one env.
    ``results_plot``: also write the results' figure to this path (implies ``results``)."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise FileNotFoundError(f"no sweep dir {sweep_dir}")
    target = Threshold(threshold_metric or metric, threshold) if threshold is not None else None
    sweep = read_sweep(sweep_dir, metric, other_metrics=(target.metric,) if target else ())
    for job in sweep.jobs:  # one line per damaged job dir (report.md lists each file too)
        if job.problems:
            log.warning("rlexp report: %s: %s", job.path, "; ".join(job.problems))
    if not sweep.jobs and sweep.plan.jobs is None:
        raise FileNotFoundError(
            f"no jobs under {sweep_dir} (no */.hydra/overrides.yaml) and no multirun.yaml: "
            "is it a multirun dir?"
        )
    results = True if results_plot is not None else results
    if results is None:
        results = varies_env(sweep.jobs)
    if results:
        add_histories(sweep.jobs, RESULT_METRICS)
    stats = summarize(sweep.jobs, target)
    per_env = env_results(sweep.jobs) if results else []
    md = to_markdown(sweep_dir, sweep, stats, metric, results_markdown(per_env) if results else ())
    trials = optuna_markdown(sweep_dir)  # an Optuna sweep: its study's trials
    if trials:
        md += "\n".join(trials) + "\n"
    confirmed = confirm_lines(sweep_dir)  # the best trials re-run on fresh seeds
    if confirmed:
        md += "\n".join(confirmed) + "\n"
    pbt = pbt_markdown(sweep_dir, metric)  # a PBT sweep: best member, schedules, lineage
    if pbt:
        md += "\n".join(pbt)
    outputs = {"report.md": lambda p: p.write_text(md)}
    outputs["report.csv"] = lambda p: p.write_text(to_csv(stats))
    if results:
        outputs["results.csv"] = lambda p: p.write_text(results_csv(per_env))
    if plot:
        line = target.value if target and target.metric == metric else None
        outputs["curves.png"] = lambda p: plot_curves(stats, p, metric, line)
        if results:
            outputs["results.png"] = lambda p: plot_results(per_env, p)
        if pbt:
            outputs["pbt_schedules.png"] = lambda p: plot_schedules(sweep_dir, p, metric)
    _write(sweep_dir, outputs)
    if results_plot is not None:
        _write(
            Path(results_plot).parent, {Path(results_plot).name: lambda p: plot_results(per_env, p)}
        )
    return md


def _write(where: Path, outputs: dict[str, Callable[[Path], object]]) -> None:
    """Write each output into ``where``; say what was written, and in one warning what could not
    be (a read-only dir, a full disk)."""
    written, failed = [], []
    for name, write in outputs.items():
        try:
            write(where / name)
            written.append(name)
        except OSError as exc:
            failed.append((name, exc.strerror or first_line(exc)))
    if written:
        log.info("wrote %s into %s", ", ".join(written), where)
    if failed:
        names = ", ".join(name for name, _ in failed)
        log.warning("rlexp report: could not write %s into %s (%s)", names, where, failed[0][1])
