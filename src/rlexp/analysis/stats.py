"""Statistics over seeds that ``rlexp report`` and ``rlexp compare`` share, one implementation each:
the interquartile mean and its 95% percentile-bootstrap interval (rliable's recommendation for few
seeds), the IQM band of learning curves, the probability of improvement and the stratified
bootstrap of two samples, and the steps a run took to reach a threshold.

Memory stays bounded as runs grow: every bootstrap works in chunks of at most BOOT_ELEMENTS
resampled values (over steps, over resamples: a 500-job sweep once took 6 GB holding steps x
resamples x seeds at once). The chunks draw the same resamples from the same seeded stream in the
same order, so the results are those of one call over everything, bit for bit."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

#: Bootstrap resamples of every interval here (percentile intervals, seeded: reproducible output).
N_BOOT = 5000
#: Steps bootstrapped in one call in ``curve_band`` at most (fewer when seeds are many).
BAND_ROWS = 200
#: Resampled values (float64) one bootstrap call holds at most (8 MB an array; a call has a few).
BOOT_ELEMENTS = 1 << 20
#: Consecutive logged values at or above a threshold that count as holding it, not a lucky eval.
IN_A_ROW = 3


def iqm(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean: the mean of the middle 50% (robust with few seeds)."""
    from scipy.stats import trim_mean

    return trim_mean(x, 0.25, axis=axis)


def _batch(n: int, rows: int = 1) -> int:
    """Resamples per vectorised call so that ``rows`` x resamples x ``n`` values fit BOOT_ELEMENTS
    (scipy draws batches in sequence from one stream: the same resamples as one call)."""
    return max(1, min(N_BOOT, BOOT_ELEMENTS // max(1, n * rows)))


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
        batch=_batch(len(x)),
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
    values' range; with one seed, or all seeds equal, the band is that value. Steps are
    bootstrapped a few at a time (each call draws the same resamples from a fresh stream, so a
    step's interval does not depend on which others share its call)."""
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
        spread = np.flatnonzero((x.shape[1] > 1) & ~np.all(x == x[:, :1], axis=1))
        per_call = max(1, min(BAND_ROWS, BOOT_ELEMENTS // (N_BOOT * x.shape[1])))
        for start in range(0, len(spread), per_call):
            rows = spread[start : start + per_call]
            res = bootstrap(
                (x[rows],),
                iqm,
                confidence_level=0.95,
                n_resamples=N_BOOT,
                batch=_batch(x.shape[1], len(rows)),
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
    return steps, _interpolated([np.array(c, dtype=float).T for c in curves], steps)


def _interpolated(curves: Sequence[np.ndarray], steps: np.ndarray) -> np.ndarray:
    """Runs x ``steps``: each (steps, values) curve interpolated inside its own range, else NaN."""
    ys = np.full((len(curves), len(steps)), np.nan)
    for i, (cs, cv) in enumerate(curves):
        inside = (steps >= cs[0]) & (steps <= cs[-1])
        ys[i, inside] = np.interp(steps[inside], cs, cv)
    return ys


def iqm_band(
    curves: Sequence[Sequence[tuple[int, float]]], seed: int = 0
) -> tuple[np.ndarray, ...]:
    """(steps, IQM, CI low, CI high) of learning curves: ``curve_band`` over the runs that cover
    each step of ``on_common_steps``, a slice of steps at a time (runs logged at other steps make
    runs x steps large)."""
    steps = np.array(sorted({step for c in curves for step, _ in c}), dtype=float)
    arrays = [np.array(c, dtype=float).T for c in curves]
    band = [np.full(len(steps), np.nan) for _ in range(3)]
    width = max(1, BOOT_ELEMENTS // max(1, len(curves)))
    for start in range(0, len(steps), width):
        part = curve_band(_interpolated(arrays, steps[start : start + width]), seed)
        for out, values in zip(band, part, strict=True):
            out[start : start + len(values)] = values
    return (steps, *band)


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
    bootstrap for one task). In chunks of resamples: x's indices come first in the seeded stream,
    then y's (as one draw of each), so a second stream from the seed, moved past x's draws, gives
    y's chunk by chunk."""
    chunk = max(1, BOOT_ELEMENTS // max(1, len(x) + len(y)))
    sizes = [min(chunk, N_BOOT - start) for start in range(0, N_BOOT, chunk)]
    rng_x, rng_y = np.random.default_rng(seed), np.random.default_rng(seed)
    for k in sizes:
        rng_y.integers(0, len(x), (k, len(x)))
    values = []
    for k in sizes:
        xs = x[rng_x.integers(0, len(x), (k, len(x)))]
        ys = y[rng_y.integers(0, len(y), (k, len(y)))]
        values.append(np.asarray(statistic(xs, ys)))
    low, high = np.percentile(np.concatenate(values), [2.5, 97.5])
    return float(low), float(high)


def steps_to_threshold(
    points: Iterable[tuple[int, float | None]], threshold: float, in_a_row: int = 1
) -> int | None:
    """The step where a metric's history first holds at or above ``threshold`` for ``in_a_row``
    consecutive logged values (1: the first value that reaches it); None when it never does.
    ``points`` are (step, value) in any order; a missing or non-finite value is skipped (it neither
    counts nor breaks a run), and of two values at one step the later wins, as
    ``rlexp.analysis.report.read_metrics``."""
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
