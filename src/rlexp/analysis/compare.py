"""``rlexp compare RUN_OR_SWEEP_DIR ...``: what differs between runs, and what it changes.

Each argument is a run dir or a dir of run dirs (a sweep, ``outputs/``), from any sweep. The
comparison shows: the config keys whose values differ (flattened ``config.yaml``) and the git
commits; per run its status, steps, final and best value of the metric (and with ``--threshold``
the steps it took to reach a level); and, when the runs form several configurations with two or
more results each, per configuration the IQM of the final values with a 95% bootstrap CI, and per
pair the difference of their IQMs and the probability of improvement P(X > Y) as rliable defines
it, each with a 95% stratified bootstrap CI. A configuration is, by default, a dir argument and
the config less the seed; ``--group-by KEY`` groups by config keys instead. Results are runs that
finished or were stopped early by a hook (as in ``rlexp report``).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np

from rlexp.analysis.liveness import Here
from rlexp.analysis.reporting.jobs import read_histories
from rlexp.analysis.runs import Run, RunsError, check_key, find_run_dirs, read_run, warn_problems
from rlexp.analysis.stats import (
    IN_A_ROW,
    _poi_rows,
    bootstrap_ci,
    iqm,
    iqm_band,
    probability_of_improvement,
    reached_stats,
    steps_to_threshold,
    stratified_bootstrap,
)
from rlexp.common.table import format_number, print_table

#: Config keys that say how a run ran, not what it trains: left out of the default grouping.
NOT_CONFIGURATION = (
    "seed",
    "trainer.device",
    "trainer.progress",
    "trainer.resume",
    "trainer.strict_device",
    "trainer.torch_threads",
    "trainer.stall_timeout_s",  # how a stuck run is told and ended
    "trainer.stop_grace_s",
    "algorithm.compile",
    "logger.",
)
#: Runs shown side by side in the differences table; more are summarised per value.
SIDE_BY_SIDE = 6
RESULT_STATES = ("finished", "stopped_early", "pruned")


@dataclass
class Member:
    """One run in the comparison: its row, metric history and scores."""

    run: Run
    source: int  # which dir argument it came from
    label: str = ""
    curve: list[tuple[int, float]] = field(default_factory=list)
    final: float | None = None
    best: float | None = None
    reached: int | None = None  # steps to the threshold (the first logged value at or above)
    reached_row: int | None = None  # the first of IN_A_ROW logged values at or above it
    group: str = ""

    @property
    def result(self) -> bool:
        return self.run.status in RESULT_STATES and self.final is not None


@dataclass
class Group:
    """A configuration: its runs and the statistics over their final values."""

    label: str
    members: list[Member]

    @property
    def finals(self) -> np.ndarray:
        return np.array([m.final for m in self.members if m.result], dtype=float)


# -- statistics (the arithmetic is rlexp.analysis.stats') ---------------------------------------------------
def compare_pair(a: Group, b: Group) -> dict[str, Any]:
    """IQM(a) - IQM(b) and P(a > b), each with its stratified bootstrap CI."""
    x, y = a.finals, b.finals
    return {
        "a": a.label,
        "b": b.label,
        "iqm_difference": float(iqm(x) - iqm(y)),
        "iqm_difference_ci": stratified_bootstrap(
            x, y, lambda p, q: iqm(p, axis=1) - iqm(q, axis=1)
        ),
        "probability_of_improvement": probability_of_improvement(x, y),
        "probability_of_improvement_ci": stratified_bootstrap(x, y, _poi_rows),
    }


def group_stats(g: Group) -> dict[str, Any]:
    """n, IQM [CI], mean of the final values, and how many reached the threshold how fast."""
    finals = g.finals
    k, median, _ = reached_stats([m.reached for m in g.members if m.result])
    return {
        "group": g.label,
        "runs": len(g.members),
        "results": len(finals),
        "iqm": float(iqm(finals)) if len(finals) else None,
        "iqm_ci": bootstrap_ci(finals, iqm) if len(finals) > 1 else None,  # as rlexp report
        "mean": float(finals.mean()) if len(finals) else None,
        "reached": k,
        "median_steps_to_threshold": None if math.isnan(median) else median,
    }


# -- reading and grouping --------------------------------------------------------------------------
def collect(
    dirs: list[str],
    metric: str,
    threshold: float | None = None,
    threshold_metric: str | None = None,
) -> list[Member]:
    """Every run under each of ``dirs``, with its history of ``metric`` (and the threshold's)."""
    here, members = Here.now(), []
    wanted = [metric] + ([threshold_metric] if threshold_metric not in (None, metric) else [])
    for source, d in enumerate(dirs):
        run_dirs = find_run_dirs([Path(d)])
        if not run_dirs:
            raise RunsError(
                f"{d}: no run dir there (none holds status.json, config.yaml or .hydra/)"
            )
        for rd in run_dirs:
            m = Member(read_run(rd, metric, here), source)
            histories, _ = read_histories(rd / "metrics.jsonl", wanted, m.run.problems)
            m.curve = histories[metric]
            m.final = m.curve[-1][1] if m.curve else m.run.last
            m.best = max(v for _, v in m.curve) if m.curve else m.run.best
            if threshold is not None:
                points = histories[threshold_metric or metric]
                m.reached = steps_to_threshold(points, threshold)
                m.reached_row = steps_to_threshold(points, threshold, IN_A_ROW)
            members.append(m)
    # Paths as found, not resolved: a symlinked run dir is labelled by its link.
    common = os.path.commonpath([os.path.abspath(m.run.path) for m in members])
    for m in members:
        m.label = (
            os.path.relpath(os.path.abspath(m.run.path), common)
            if len(members) > 1
            else m.run.path.name
        )
        if m.label == ".":
            m.label = m.run.path.name
    return members


def _configuration(config: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in config.items() if not k.startswith(NOT_CONFIGURATION)}


def _frozen(config: dict[str, Any]) -> str:
    return json.dumps(config, sort_keys=True, default=str)


def make_groups(members: list[Member], dirs: list[str], group_by: list[str] = ()) -> list[Group]:
    """Configurations: by the ``group_by`` keys' values, else by (dir argument, config less seed)."""
    for key in group_by:
        check_key(key, [m.run for m in members], "--group-by")
    keyed: dict[tuple, list[Member]] = {}
    for m in members:
        if group_by:
            key = tuple(f"{k}={m.run.config.get(k, '-')}" for k in group_by)
        else:
            key = (m.source if len(dirs) > 1 else 0, _frozen(_configuration(m.run.config)))
        keyed.setdefault(key, []).append(m)
    labels = [" ".join(k) for k in keyed] if group_by else _default_labels(keyed, dirs)
    groups = [Group(label, ms) for label, ms in zip(labels, keyed.values(), strict=True)]
    for g in groups:
        for m in g.members:
            m.group = g.label
    return groups


def _default_labels(keyed: dict[tuple, list[Member]], dirs: list[str]) -> list[str]:
    """A dir argument (when several were given) and the overrides, or else the config keys, that
    set a configuration apart from the others."""
    confs = [_configuration(ms[0].run.config) for ms in keyed.values()]
    differ = sorted(
        k for k in {k for c in confs for k in c} if len({_frozen({0: c.get(k)}) for c in confs}) > 1
    )
    shared = set.intersection(*(set(_overrides(ms)) for ms in keyed.values()))
    labels = []
    for (source, _), ms, conf in zip(keyed, keyed.values(), confs, strict=True):
        parts = [dirs[source]] if len(dirs) > 1 else []
        own = [o for o in _overrides(ms) if o not in shared]
        if differ:
            parts += own or [f"{k}={conf.get(k, '-')}" for k in differ[:3]] + (
                ["..."] if len(differ) > 3 else []
            )
        labels.append(" ".join(parts) or "(all runs)")
    return labels


def _overrides(members: list[Member]) -> list[str]:
    """The overrides every member shares, less the seed."""
    lists = [
        [o for o in m.run.overrides if o.partition("=")[0].lstrip("+~") != "seed"] for m in members
    ]
    return [o for o in lists[0] if all(o in rest for rest in lists[1:])]


def differences(members: list[Member]) -> dict[str, dict[str, Any]]:
    """Config keys (and ``git``) whose values differ between runs: key -> run label -> value."""
    keys = sorted({k for m in members for k in m.run.config})
    out = {}
    for key in [*keys, "git"]:
        values = {
            m.label: (m.run.git if key == "git" else m.run.config.get(key, "-")) for m in members
        }
        if len({_frozen({0: v}) for v in values.values()}) > 1:
            out[key] = values
    return out


# -- output ----------------------------------------------------------------------------------------
def _ci(ci: tuple[float, float] | None) -> str:
    return "" if ci is None else f" [{format_number(ci[0])}, {format_number(ci[1])}]"


def _steps(step: float | None) -> str:
    return "-" if step is None else f"{step:.0f}"


def _value_text(value: Any) -> str:
    return "-" if value is None else str(value)


def print_differences(diffs: dict[str, dict[str, Any]], members: list[Member]) -> None:
    """Keys as rows; the runs as columns when few, else each value with the runs that have it."""
    if not diffs:
        print("Config: the same in every run (git commit too).\n")
        return
    if len(members) <= SIDE_BY_SIDE:
        rows = [[k, *(_value_text(v[m.label]) for m in members)] for k, v in diffs.items()]
        print_table(
            ["key", *(m.label for m in members)],
            rows,
            title=f"Config keys that differ ({len(diffs)})",
        )
    else:
        rows = []
        for key, values in diffs.items():
            by_value: dict[str, list[str]] = {}
            for label, v in values.items():
                by_value.setdefault(_value_text(v), []).append(label)
            rows.append([key, "; ".join(f"{v} ({_few(ls)})" for v, ls in by_value.items())])
        print_table(["key", "values (runs)"], rows, title=f"Config keys that differ ({len(diffs)})")
    print()


def _few(labels: list[str]) -> str:
    return ", ".join(labels[:3]) + (f" +{len(labels) - 3} more" if len(labels) > 3 else "")


def print_comparison(
    members: list[Member],
    groups: list[Group],
    diffs: dict,
    pairs: list[dict],
    metric: str,
    threshold: float | None,
) -> None:
    """The differences, the runs, the configurations and their pairwise comparisons."""
    print_differences(diffs, members)
    head = ["run", "group", "status", "steps", f"final {metric}", "best", "git"]
    if threshold is not None:
        head += [f"steps to {threshold:g}", f"({IN_A_ROW} in a row)"]
    rows = []
    for m in members:
        row = [
            m.label,
            m.group,
            m.run.status,
            _steps(m.run.step),
            format_number(m.final),
            format_number(m.best),
            m.run.git or "-",
        ]
        rows.append(
            row + ([_steps(m.reached), _steps(m.reached_row)] if threshold is not None else [])
        )
    print_table(head, rows, right={3, 4, 5, 7, 8}, title=f"Runs ({len(members)})")
    stats = [group_stats(g) for g in groups]
    if len(groups) > 1:
        rows = [
            [
                s["group"],
                f"{s['results']}/{s['runs']}",
                format_number(s["iqm"]) + _ci(s["iqm_ci"]),
                format_number(s["mean"]),
            ]
            for s in stats
        ]
        head = ["configuration", "results", "IQM [95% CI]", "mean"]
        if threshold is not None:
            head.append("reached (median steps)")
            for row, s in zip(rows, stats, strict=True):
                row.append(
                    f"{s['reached']}/{s['results']} ({_steps(s['median_steps_to_threshold'])})"
                )
        print()
        print_table(head, rows, right={1, 3}, title=f"Configurations ({len(groups)})")
    print()
    left_out = [g.label for g in groups if len(g.finals) < 2]
    if not pairs:
        print(_why_no_pairs(groups) + "\n")
    elif left_out:
        print(f"Not compared (fewer than two results): {', '.join(left_out)}\n")
    for p in pairs:
        low, high = p["probability_of_improvement_ci"]
        print(f"{p['a']}  vs  {p['b']}:")
        print(
            f"  IQM(first) - IQM(second)  {format_number(p['iqm_difference'])}"
            f"{_ci(p['iqm_difference_ci'])}"
        )
        print(
            f"  P(first > second)         {p['probability_of_improvement']:.3f}"
            f" [{low:.3f}, {high:.3f}]\n"
        )
    print(
        f"Scores: the last {metric} of each run that finished or was stopped early; IQM: "
        "interquartile mean; CIs: 95% percentile bootstrap over runs."
    )


def _why_no_pairs(groups: list[Group]) -> str:
    if len(groups) < 2:
        return (
            "One configuration: no comparison between configurations (give two sweeps, or "
            "--group-by KEY)."
        )
    return (
        "No comparison between configurations: each needs two or more runs that finished "
        "with the metric."
    )


def plot_curves(
    groups: list[Group], path: Path, metric: str, threshold: float | None = None
) -> None:
    """Per configuration, the IQM over its runs at each logged step with a 95% bootstrap band
    (which stays inside the runs' values at that step), from every run with a history."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    for g in groups:
        curves = [m.curve for m in g.members if m.curve]
        if not curves:
            continue
        steps, centre, low, high = iqm_band(curves)
        (line,) = ax.plot(steps, centre, label=f"{g.label} (n={len(curves)})")
        ax.fill_between(steps, low, high, alpha=0.2, color=line.get_color(), linewidth=0)
    if threshold is not None:
        ax.axhline(
            threshold, color="gray", linestyle="--", linewidth=1, label=f"threshold {threshold:g}"
        )
    ax.set(xlabel="env steps", ylabel=metric, title="IQM over runs, 95% bootstrap CI")
    ax.grid(alpha=0.3)
    if ax.lines:
        ax.legend(fontsize="small")
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=120)
    except OSError as exc:
        raise RunsError(f"{path}: cannot write the plot ({exc.strerror or exc})") from None
    finally:
        plt.close(fig)


def main(
    dirs: list[str],
    metric: str,
    threshold: float | None = None,
    threshold_metric: str | None = None,
    group_by: list[str] = (),
    plot: str | None = None,
    as_json: bool = False,
) -> None:
    """``rlexp compare``: RunsError (one line) for a dir without runs or an unknown key."""
    for d in dirs:
        if not Path(d).is_dir():
            raise RunsError(f"{d}: no such dir")
    members = collect(dirs, metric, threshold, threshold_metric)
    groups = make_groups(members, dirs, list(group_by))
    diffs = differences(members)
    warn_problems([m.run for m in members], "compare")  # after the configs were read
    usable = [g for g in groups if len(g.finals) >= 2]
    pairs = [compare_pair(a, b) for a, b in combinations(usable, 2)]
    if plot:
        plot_curves(
            groups, Path(plot), metric, threshold if threshold_metric in (None, metric) else None
        )
    if as_json:
        runs = [
            {
                **m.run.to_json(),
                "label": m.label,
                "group": m.group,
                "final": m.final,
                "best": m.best,
                "steps_to_threshold": m.reached,
                "steps_to_threshold_in_a_row": m.reached_row,
            }
            for m in members
        ]
        out = {
            "metric": metric,
            "threshold": threshold,
            "runs": runs,
            "differences": diffs,
            "groups": [group_stats(g) for g in groups],
            "comparisons": pairs,
        }
        print(json.dumps(out, indent=2, default=str))
        return
    print_comparison(members, groups, diffs, pairs, metric, threshold)
    if plot:
        print(f"curves: {plot}")
