"""Statistics over seeds that ``rlexp report`` and ``rlexp compare`` share, one implementation each:
the interquartile mean and its 95% percentile-bootstrap interval (rliable's recommendation for few
seeds), the IQM band of learning curves, the probability of improvement and the stratified
bootstrap of two samples, and the steps a run took to reach a threshold."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

#: Bootstrap resamples of every interval here (percentile intervals, seeded: reproducible output).
N_BOOT = 5000
#: Steps bootstrapped in one call in ``curve_band`` (memory: rows x N_BOOT resamples x seeds).
BAND_ROWS = 200
#: Consecutive logged values at or above a threshold that count as holding it, not a lucky eval.
IN_A_ROW = 3


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
        n_resamples=N_BOOT,
        method="percentile",
        vectorized=True,
        random_state=np.random.default_rng(seed),
    )
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


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
                n_resamples=N_BOOT,
                method="percentile",
                vectorized=True,
                axis=-1,
                random_state=np.random.default_rng(seed),
            )
            low[cols[rows]] = res.confidence_interval.low
            high[cols[rows]] = res.confidence_interval.high
    return center, low, high


def on_common_steps(curves: Sequence[Sequence[tuple[int, float]]]) -> tuple[np.ndarray, np.ndarray]:
    """(steps, values): curves of (step, value) linearly interpolated onto the union of their
    steps (runs evaluate at the same steps unless configs differ), each only inside its own range;
    values is runs x steps, NaN outside a run's range."""
    steps = np.array(sorted({step for c in curves for step, _ in c}), dtype=float)
    ys = np.full((len(curves), len(steps)), np.nan)
    for i, c in enumerate(curves):
        cs, cv = np.array(c, dtype=float).T
        inside = (steps >= cs[0]) & (steps <= cs[-1])
        ys[i, inside] = np.interp(steps[inside], cs, cv)
    return steps, ys


def iqm_band(
    curves: Sequence[Sequence[tuple[int, float]]], seed: int = 0
) -> tuple[np.ndarray, ...]:
    """(steps, IQM, CI low, CI high) of learning curves: ``curve_band`` over the runs that cover
    each step of ``on_common_steps``."""
    steps, ys = on_common_steps(curves)
    return (steps, *curve_band(ys, seed))


def probability_of_improvement(x: np.ndarray, y: np.ndarray) -> float:
    """rliable's P(X > Y): the mean over all pairs (x_i, y_j) of 1[x_i > y_j] + 1[x_i = y_j] / 2."""
    x, y = np.asarray(x, float)[:, None], np.asarray(y, float)[None, :]
    return float(np.mean((x > y) + 0.5 * (x == y)))


def _poi_rows(xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """P(X > Y) for each row pair of two (resamples, runs) arrays, through the Mann-Whitney U
    (average ranks count a tie as one half): U_x / (m n)."""
    from scipy.stats import rankdata

    m, n = xs.shape[1], ys.shape[1]
    ranks = rankdata(np.concatenate([xs, ys], axis=1), axis=1)
    return (ranks[:, :m].sum(axis=1) - m * (m + 1) / 2) / (m * n)


def stratified_bootstrap(
    x: np.ndarray,
    y: np.ndarray,
    statistic: Callable[[np.ndarray, np.ndarray], Any],
    seed: int = 0,
) -> tuple[float, float]:
    """95% percentile interval of ``statistic(xs, ys)`` (row-wise over resamples) when the runs of
    each sample are resampled with replacement, each sample on its own (rliable's stratified
    bootstrap for one task)."""
    rng = np.random.default_rng(seed)
    xs = x[rng.integers(0, len(x), (N_BOOT, len(x)))]
    ys = y[rng.integers(0, len(y), (N_BOOT, len(y)))]
    low, high = np.percentile(statistic(xs, ys), [2.5, 97.5])
    return float(low), float(high)


def steps_to_threshold(
    points: Iterable[tuple[int, float | None]], threshold: float, in_a_row: int = 1
) -> int | None:
    """The step where a metric's history first holds at or above ``threshold`` for ``in_a_row``
    consecutive logged values (1: the first value that reaches it); None when it never does.
    ``points`` are (step, value) in any order; a missing or non-finite value is skipped (it neither
    counts nor breaks a run), and of two values at one step the later wins, as
    ``rlexp.report.read_metrics``."""
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
