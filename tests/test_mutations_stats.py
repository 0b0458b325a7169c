"""rlexp's statistics over seeds against independent references (issue #35): hand-computed
literals, scipy, and *exact* bootstrap distributions, on asymmetric data (IQM != mean, median !=
mean), so that an IQM computed as the plain mean, a 90% interval labelled 95%, or two samples
resampled as one fails.

A percentile-bootstrap interval is two quantiles of the statistic's bootstrap distribution. For the
data here that distribution is known exactly, without drawing anything:

- ``n`` values of which ``k`` are 1 and the rest 0: a resample's number of ones is Binomial(n, k/n);
  its mean is that count / n, and its IQM (scipy's trim_mean(., 0.25): the middle n - 2 floor(n/4)
  sorted values) is clip(count - floor(n/4), 0, n - 2 floor(n/4)) / (n - 2 floor(n/4)).
- 8 values: all 6435 multisets a resample can be, each with its multinomial probability.

rlexp draws N_BOOT = 5000 resamples, so its interval is within Monte-Carlo error of the exact one;
the tolerances below are a few times that error and well under the distance to the 5% / 95%
quantiles (a 90% interval): with seeds 0-19 the code passes every time and a 90% interval fails
every time.
"""

from __future__ import annotations

import itertools
import math
import statistics
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import binom, trim_mean

from rlexp.analysis import compare, stats
from rlexp.analysis.reporting.jobs import Job
from rlexp.analysis.reporting.results import over_seeds
from rlexp.analysis.reporting.summary import summarize

# ------------------------------------------------------------------------------- references


def quantile(values: np.ndarray, probs: np.ndarray, q: float) -> float:
    """The q-quantile of the discrete distribution putting mass ``probs`` on ``values``."""
    order = np.argsort(values, kind="stable")
    return float(values[order][np.searchsorted(np.cumsum(probs[order]), q)])


def binary(n: int, k: int) -> np.ndarray:
    """``k`` ones and ``n - k`` zeros, unsorted (ones first)."""
    return np.array([1.0] * k + [0.0] * (n - k))


def binary_bootstrap(n: int, k: int, statistic: str) -> tuple[np.ndarray, np.ndarray]:
    """The exact bootstrap distribution of the mean or the IQM of ``binary(n, k)``."""
    ones = np.arange(n + 1)
    probs = binom.pmf(ones, n, k / n)
    if statistic == "mean":
        return ones / n, probs
    g = n // 4
    return np.clip(ones - g, 0, n - 2 * g) / (n - 2 * g), probs


def difference(a, b) -> tuple[np.ndarray, np.ndarray]:
    """The distribution of A - B for independent A, B."""
    (va, pa), (vb, pb) = a, b
    return (va[:, None] - vb[None, :]).ravel(), (pa[:, None] * pb[None, :]).ravel()


def exact_interval(dist, level: float = 0.95) -> tuple[float, float]:
    tail = (1 - level) / 2
    return quantile(*dist, tail), quantile(*dist, 1 - tail)


#: Eight final scores of a few-seed sweep, with one outlier: mean 15.75, IQM 4.0, median 3.5.
FINALS = [3.0, 0.0, 9.0, 100.0, 2.0, 7.0, 4.0, 1.0]


def multiset_bootstrap(x: list[float], statistic) -> tuple[np.ndarray, np.ndarray]:
    """The exact bootstrap distribution of ``statistic`` (of a sorted resample) for few values."""
    n, xs = len(x), np.sort(x)
    values, probs = [], []
    for idx in itertools.combinations_with_replacement(range(n), n):
        counts = np.bincount(idx, minlength=n)
        ways = math.factorial(n) / math.prod(math.factorial(int(c)) for c in counts)
        values.append(statistic(xs[list(idx)]))
        probs.append(ways / n**n)
    return np.array(values), np.array(probs)


def hand_iqm_of_sorted_8(s: np.ndarray) -> float:
    return float(s[2:6].mean())  # 8 values: drop the lowest two and the highest two


# ---------------------------------------------------------------------------------------- IQM


def test_iqm_is_the_mean_of_the_middle_half_not_the_mean():
    # sorted 0 1 2 3 4 7 9 100: the middle four 2 3 4 7
    assert float(stats.iqm(np.array(FINALS))) == 4.0
    assert np.mean(FINALS) == 15.75  # what a plain mean would give
    # 5 values: scipy trims floor(0.25 * 5) = 1 from each end: (2 + 4 + 8) / 3
    assert float(stats.iqm(np.array([8.0, 1.0, 100.0, 2.0, 4.0]))) == pytest.approx(14 / 3)
    # 7 values: floor(1.75) = 1 from each end: (1 + 2 + 6 + 10 + 11) / 5
    assert float(stats.iqm(np.array([50.0, 11, 1, 0, 10, 2, 6]))) == pytest.approx(6.0)
    rows = np.array([FINALS, [5.0, 5.0, 5.0, 5.0, 5.0, 5.0, 5.0, -95.0]])
    assert stats.iqm(rows, axis=1) == pytest.approx([4.0, 5.0])
    assert stats.iqm(rows.T, axis=0) == pytest.approx([4.0, 5.0])
    x = np.random.default_rng(3).lognormal(size=37)  # skewed: mean well above the IQM
    assert float(stats.iqm(x)) == pytest.approx(trim_mean(x, 0.25))
    assert float(stats.iqm(x)) < 0.9 * x.mean()


def test_reached_stats_median_and_iqm_of_skewed_steps():
    # reached: 100 200 250 300 400 10000 (6 of 8). median (250 + 300) / 2; IQM: trim 1 + 1
    k, median, iqm = stats.reached_stats([400, None, 100, 300, 200, None, 10_000, 250])
    assert (k, median, iqm) == (6, 275.0, pytest.approx(1150 / 4))
    k, median, iqm = stats.reached_stats([900, 100, 200])  # odd: the middle one; IQM trims none
    assert (k, median, iqm) == (3, 200.0, pytest.approx(400.0))


# -------------------------------------------------------------------- intervals: exact bootstrap


def test_bootstrap_ci_of_the_iqm_is_the_exact_95_percent_interval():
    x = binary(400, 160)  # mean 0.4, IQM 0.3 (sorted: 240 zeros, 160 ones; the middle 200: 60 ones)
    assert float(stats.iqm(x)) == pytest.approx(0.3)
    exact = exact_interval(binary_bootstrap(400, 160, "iqm"))
    assert exact == pytest.approx((0.205, 0.395))  # the 90% interval would be (0.22, 0.38)
    assert stats.bootstrap_ci(x, stats.iqm) == pytest.approx(exact, abs=0.0075)


def test_bootstrap_ci_of_the_mean_is_the_exact_95_percent_interval():
    x = binary(400, 160)
    exact = exact_interval(binary_bootstrap(400, 160, "mean"))
    assert exact == pytest.approx((0.3525, 0.4475))  # 90%: (0.36, 0.44)
    assert stats.bootstrap_ci(x, np.mean) == pytest.approx(exact, abs=0.004)


def test_curve_band_is_the_iqm_and_its_exact_95_percent_interval():
    ys = np.stack([binary(400, 160), binary(400, 220)], axis=1)  # 400 seeds x 2 steps
    center, low, high = stats.curve_band(ys)
    # step 2: 180 zeros, 220 ones; the middle 200 (sorted 100..299): 80 zeros, 120 ones
    assert center == pytest.approx([0.3, 0.6])
    for j, k in enumerate((160, 220)):
        exact = exact_interval(binary_bootstrap(400, k, "iqm"))
        assert (low[j], high[j]) == pytest.approx(exact, abs=0.0075)


def test_few_seed_interval_of_the_report_is_the_exact_95_percent_interval():
    """8 skewed finals, as ``rlexp report`` / ``results`` / ``compare`` summarise them: the IQM and
    its interval against every resample there can be."""
    exact = exact_interval(multiset_bootstrap(FINALS, hand_iqm_of_sorted_8))
    assert exact == (1.5, 30.0)  # 90%: (1.75, 28.25)
    stats_report = summarize(
        [
            Job(Path(f"/s/{i}"), [f"seed={i}"], str(i), "finished", 100, curve=[(100, v)])
            for i, v in enumerate(FINALS)
        ]
    )
    (s,) = stats_report
    assert (s.iqm, s.mean) == (4.0, 15.75)
    assert s.std == pytest.approx(statistics.stdev(FINALS))
    assert s.iqm_ci[0] == pytest.approx(exact[0], abs=0.3)
    assert s.iqm_ci[1] == pytest.approx(exact[1], abs=0.5)
    exact_mean = exact_interval(multiset_bootstrap(FINALS, np.mean))
    assert s.mean_ci == pytest.approx(exact_mean, abs=0.5)

    o = over_seeds(FINALS)
    assert (o.iqm, o.mean, o.std) == (4.0, 15.75, pytest.approx(statistics.stdev(FINALS)))
    assert o.iqm_ci[1] == pytest.approx(exact[1], abs=0.5)

    group = compare.Group("g", [_member(v) for v in FINALS])
    g = compare.group_stats(group)
    assert (g["iqm"], g["mean"], g["results"]) == (4.0, 15.75, 8)
    assert g["iqm_ci"][1] == pytest.approx(exact[1], abs=0.5)


def _member(final: float, reached: int | None = None) -> compare.Member:
    return compare.Member(
        run=SimpleNamespace(status="finished"), source=0, final=final, reached=reached
    )


def test_compare_group_median_steps_to_threshold_of_skewed_steps():
    members = [_member(1.0, r) for r in (100, 200, 10_000, None)]
    g = compare.group_stats(compare.Group("g", members))
    assert (g["reached"], g["median_steps_to_threshold"]) == (3, 200.0)


# -------------------------------------------------------------------- the stratified bootstrap


def test_stratified_bootstrap_takes_the_2_5_and_97_5_percentiles():
    """A statistic whose values over the resamples are uniform on [0, 1], whatever was drawn: its
    95% percentile interval is (0.025, 0.975) exactly; a 90% one would be (0.05, 0.95)."""

    def uniform(xs, ys):
        return np.linspace(0.0, 1.0, len(xs))

    x, y = np.array([1.0, 5.0, 2.0]), np.array([7.0, 3.0])
    assert stats.stratified_bootstrap(x, y, uniform) == pytest.approx((0.025, 0.975), abs=1e-3)


def test_stratified_bootstrap_resamples_each_sample_on_its_own():
    """mean(xs) - mean(ys) for two binary samples of different sizes: the difference of two
    independent scaled binomials. Pooling the samples, or a 90% interval, is far off."""
    x, y = binary(300, 90), binary(100, 50)
    exact = exact_interval(
        difference(binary_bootstrap(300, 90, "mean"), binary_bootstrap(100, 50, "mean"))
    )
    assert exact == pytest.approx((-0.31, -0.09))  # 90%: (-0.293, -0.107)
    got = stats.stratified_bootstrap(x, y, lambda p, q: p.mean(axis=1) - q.mean(axis=1))
    assert got == pytest.approx(exact, abs=0.0075)


def test_compare_pair_iqm_difference_and_probability_of_improvement_with_exact_intervals():
    x, y = binary(400, 160), binary(200, 130)  # IQMs 0.3 and 0.8 (means 0.4, 0.65)
    pair = compare.compare_pair(
        compare.Group("a", [_member(v) for v in x]), compare.Group("b", [_member(v) for v in y])
    )
    assert pair["iqm_difference"] == pytest.approx(-0.5)  # the means' difference is -0.25
    # P(X > Y) = P(1, 0) + P(equal) / 2 = 0.4 * 0.35 + (0.4 * 0.65 + 0.6 * 0.35) / 2
    assert pair["probability_of_improvement"] == pytest.approx(0.375)

    iqm_diff = difference(binary_bootstrap(400, 160, "iqm"), binary_bootstrap(200, 130, "iqm"))
    exact = exact_interval(iqm_diff)
    assert exact == pytest.approx((-0.66, -0.335))  # 90%: (-0.635, -0.36)
    assert pair["iqm_difference_ci"] == pytest.approx(exact, abs=0.0125)

    # P(X > Y) of a resample with a ones of 400 and b ones of 200: a/400 (1 - b/200) + ties / 2
    px = np.arange(401)[:, None] / 400
    py = np.arange(201)[None, :] / 200
    poi = (px * (1 - py) + 0.5 * (px * py + (1 - px) * (1 - py))).ravel()
    probs = (
        binom.pmf(np.arange(401), 400, 0.4)[:, None] * binom.pmf(np.arange(201), 200, 0.65)
    ).ravel()
    exact = exact_interval((poi, probs))
    assert exact == pytest.approx((0.335, 0.41625))  # 90%: (0.34125, 0.41)
    assert pair["probability_of_improvement_ci"] == pytest.approx(exact, abs=0.003)


def test_probability_of_improvement_is_not_symmetric_in_its_arguments():
    # 5 beats 1 and 2, loses to 7; 6 the same: 4 of 6 pairs
    assert stats.probability_of_improvement([5, 6], [1, 2, 7]) == pytest.approx(4 / 6)
    assert stats.probability_of_improvement([1, 2, 7], [5, 6]) == pytest.approx(2 / 6)
    # ties count a half: 2 = 2 once, 3 > 2 once, 2 < 4, 3 < 4 -> (0.5 + 1) / 4
    assert stats.probability_of_improvement([2, 3], [2, 4]) == pytest.approx(0.375)


# ------------------------------------------------------------------------- curves on common steps


def test_on_common_steps_interpolates_each_curve_inside_its_own_range():
    a = [(0, 0.0), (100, 10.0)]
    b = [(50, 4.0), (150, 8.0)]
    steps, ys = stats.on_common_steps([a, b])
    assert list(steps) == [0.0, 50.0, 100.0, 150.0]
    assert np.array_equal(ys[0], [0.0, 5.0, 10.0, np.nan], equal_nan=True)
    assert np.array_equal(ys[1], [np.nan, 4.0, 6.0, 8.0], equal_nan=True)
    steps, center, low, high = stats.iqm_band([a, b, [(0, 1.0), (150, 31.0)]])
    # step 100: a 10, b 6, c 1 + 30 * 100/150 = 21 -> 3 values, IQM trims none: 37 / 3
    assert center[2] == pytest.approx(37 / 3)
    assert center[0] == pytest.approx(0.5)  # a 0, c 1
