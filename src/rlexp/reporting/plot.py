"""``curves.png``: per configuration, the IQM learning curve over seeds and its 95% bootstrap band,
the table's statistic (``rlexp.stats.curve_band``)."""

from __future__ import annotations

from pathlib import Path

from rlexp.reporting.summary import ConfigStats
from rlexp.stats import iqm_band


def plot_curves(
    stats: list[ConfigStats], path: Path, metric: str, threshold: float | None = None
) -> None:
    """IQM learning curve per configuration with its 95% bootstrap band over seeds: the statistic
    of the table (``rlexp.stats.iqm_band``), so the band at the last step is the table's IQM interval."""
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
