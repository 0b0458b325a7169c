"""``curves.png`` of ``rlexp report``: the band is the table's statistic (IQM over seeds with its 95%
percentile bootstrap interval), so it agrees with report.md at the last step and never leaves the
range of the values (a t-interval on the mean drew [-800, 1650] for returns in [0, 1000])."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rlexp.analysis.report import Job, bootstrap_ci, curve_band, iqm, plot_curves, summarize

STEPS = [1000, 2000, 3000, 4000]


def job(seed: int, values: list[float], lr: str) -> Job:
    return Job(
        path=Path(f"/sweep/{lr}/{seed}"),
        overrides=[f"seed={seed}", f"algorithm.lr={lr}"],
        seed=str(seed),
        state="finished",
        global_step=STEPS[-1],
        curve=list(zip(STEPS, values, strict=True)),
    )


#: Five seeds of a task whose return lies in [0, 1000]: bimodal on the way, all 1000 at the end.
SOLVED = [
    [0, 0, 500, 1000],
    [0, 1000, 1000, 1000],
    [0, 0, 1000, 1000],
    [1000, 1000, 1000, 1000],
    [0, 0, 0, 1000],
]
#: Another configuration, spread at the end.
SPREAD = [[10, 50, 100, 150], [20, 80, 300, 700], [0, 40, 90, 120], [5, 60, 200, 900]]


def test_the_band_is_the_tables_iqm_interval_and_stays_in_the_observed_range():
    ys = np.array(SOLVED, dtype=float)
    center, low, high = curve_band(ys)
    assert (low[-1], center[-1], high[-1]) == (1000, 1000, 1000)
    for j in range(len(STEPS)):
        column = ys[:, j]
        assert column.min() <= low[j] <= center[j] <= high[j] <= column.max()
        assert center[j] == pytest.approx(float(iqm(column)))
        assert (low[j], high[j]) == pytest.approx(bootstrap_ci(column, iqm))
    # what the old band (mean +- t-interval) drew at step 2000: far outside [0, 1000]
    from scipy.stats import t

    half = t.ppf(0.975, 4) * ys[:, 1].std(ddof=1) / np.sqrt(5)
    assert ys[:, 1].mean() - half < 0 and ys[:, 1].mean() + half > 1000


def test_steps_some_seeds_did_not_log_use_the_others_and_one_seed_is_its_value():
    ys = np.array([[1.0, 5.0, np.nan], [3.0, 7.0, np.nan], [2.0, 9.0, 4.0]])
    center, low, high = curve_band(ys)
    assert (low[2], center[2], high[2]) == (4.0, 4.0, 4.0)  # only seed 3 logged step 3
    assert (low[0], high[0]) == pytest.approx(bootstrap_ci(ys[:, 0], iqm))


def test_plot_curves_draws_the_tables_interval_at_the_last_step(tmp_path, monkeypatch):
    import matplotlib.axes

    drawn = []
    real = matplotlib.axes.Axes.fill_between

    def record(self, x, y1, y2, **kw):
        drawn.append((np.asarray(x), np.asarray(y1), np.asarray(y2)))
        return real(self, x, y1, y2, **kw)

    monkeypatch.setattr(matplotlib.axes.Axes, "fill_between", record)
    jobs = [job(i, v, "1e-3") for i, v in enumerate(SOLVED)]
    jobs += [job(i, v, "3e-4") for i, v in enumerate(SPREAD)]
    stats = summarize(jobs)
    plot_curves(stats, tmp_path / "curves.png", "eval/episode_return")
    assert (tmp_path / "curves.png").stat().st_size > 0
    assert len(drawn) == 2
    for s, (x, low, high) in zip(stats, drawn, strict=True):
        assert list(x) == STEPS
        assert (low[-1], high[-1]) == pytest.approx(s.iqm_ci)  # the table's IQM [95% CI]
        values = np.array([j.curve for j in s.jobs])[:, :, 1]
        assert np.all(low >= values.min(axis=0)) and np.all(high <= values.max(axis=0))
    solved = next(s for s in stats if "1e-3" in s.label)
    assert solved.iqm_ci == (1000.0, 1000.0)
