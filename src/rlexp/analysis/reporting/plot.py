"""``curves.png``: per configuration, the IQM learning curve over seeds and its 95% bootstrap band,
the table's statistic (``rlexp.analysis.stats.curve_band``); ``results.png``: the results per env, one panel
per env with its training and eval returns and the anchors."""

from __future__ import annotations

import math
from pathlib import Path

from rlexp.analysis.reporting.anchors import EVAL, SOURCES, TRAIN
from rlexp.analysis.reporting.results import EVAL_METRIC, TRAIN_METRIC, EnvResult
from rlexp.analysis.reporting.summary import ConfigStats
from rlexp.analysis.stats import iqm_band


def plot_curves(
    stats: list[ConfigStats], path: Path, metric: str, threshold: float | None = None
) -> None:
    """IQM learning curve per configuration with its 95% bootstrap band over seeds: the statistic
    of the table (``rlexp.analysis.stats.iqm_band``), so the band at the last step is the table's IQM interval."""
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
        steps, center, low, high = iqm_band(curves)
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


def plot_results(results: list[EnvResult], path: Path) -> None:
    """The results view's curves (``results.png``): one panel per env, the IQM over seeds of the
    training return (last 100 episodes) and of the deterministic eval return vs env steps, each with
    its 95% bootstrap band (``rlexp.analysis.stats.iqm_band``), and the anchors of that env as dotted lines
    in the colour of the metric they measure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(len(results), 1)
    cols = min(n, 2)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 4 * rows), squeeze=False)
    sources = {s.key: s for s in SOURCES}
    for ax, r in zip(axes.flat, results, strict=False):
        for metric, what, color in ((TRAIN_METRIC, TRAIN, "C0"), (EVAL_METRIC, EVAL, "C1")):
            curves = [j.curves[metric] for j in r.jobs if j.curves.get(metric)]
            if curves:
                steps, center, low, high = iqm_band(curves)
                ax.plot(steps, center, color=color, label=f"{metric} (n={len(curves)})")
                ax.fill_between(steps, low, high, color=color, alpha=0.2)
            for key, anchor in r.anchors.items():
                if sources[key].measures == what:
                    label = f"{sources[key].name} {anchor.env_id}: {anchor.mean:.0f}"
                    ax.axhline(anchor.mean, color=color, linestyle=":", linewidth=1.2, label=label)
        ax.set_title(f"{r.env}" + (f" {r.label}" if r.label else ""))
        ax.set_xlabel("env steps")
        ax.set_ylabel("return")
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize="small")
    for ax in list(axes.flat)[len(results) :]:
        ax.set_visible(False)
    fig.suptitle("IQM over seeds, 95% percentile bootstrap CI (as in report.md's results per env)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
