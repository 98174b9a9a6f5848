"""Clopper-Pearson bound against closed forms and an mpmath root of the binomial tail;
pooled quantiles of log-binned times against the raw order statistics."""

import math

import mpmath as mp
import numpy as np
import pytest

from afvsgp_gym.stats import (
    BINS_PER_DECADE,
    clopper_pearson_upper,
    histogram_quantile,
    merge_histograms,
    time_histogram,
)

EPS = np.finfo(float).eps


def _binomial_cdf(k: int, n: int, p):
    """P[Binomial(n, p) <= k] summed term by term (no beta function involved), over the
    shorter of the two tails."""
    if k < n / 2:
        return mp.fsum(mp.binomial(n, i) * p**i * (1 - p) ** (n - i) for i in range(k + 1))
    return 1 - mp.fsum(mp.binomial(n, i) * p**i * (1 - p) ** (n - i)
                       for i in range(k + 1, n + 1))


def _reference_upper(k: int, n: int, confidence: float):
    """Root of P[Bin(n, p) <= k] = 1 - confidence in p (40 digits; the CDF falls from >= 1/2
    at p = k/n to 0 at p = 1), and its condition number |F / (p F'(p))|, F' = -n pmf_{n-1}(k)."""
    with mp.workdps(40):
        target = 1 - mp.mpf(confidence)
        p = mp.findroot(lambda x: _binomial_cdf(k, n, x) - target,
                        (mp.mpf(k) / n, mp.mpf(1)), solver="illinois", tol=mp.mpf(10) ** -60,
                        verify=False)
        assert abs(_binomial_cdf(k, n, p) - target) <= mp.mpf(10) ** -30 * target  # converged
        dF = n * mp.binomial(n - 1, k) * p**k * (1 - p) ** (n - 1 - k)
        return p, float(abs(target / (p * dF)))


@pytest.mark.parametrize("k, n", [(0, 1), (0, 20), (0, 1000), (1, 1000), (5, 50), (25, 50),
                                  (49, 50), (999, 1000), (3, 3000), (150, 3000)])
@pytest.mark.parametrize("confidence", [0.95, 0.99])
def test_bound_matches_the_binomial_tail_root(k, n, confidence):
    p_ref, cond = _reference_upper(k, n, confidence)
    got = clopper_pearson_upper(k, n, confidence)
    # an error of a few hundred ulp in the incomplete beta's evaluation, amplified by the
    # root's conditioning (Boost's ibeta_inv accuracy)
    tol = 500 * EPS * max(1.0, cond)
    assert abs(got - float(p_ref)) <= tol * float(p_ref), (got, float(p_ref), cond)


@pytest.mark.parametrize("n", [1, 10, 1000, 10**6])
def test_zero_events_closed_form(n):
    # P[Bin(n, p) = 0] = (1 - p)^n = 0.05  =>  p = 1 - 0.05^(1/n) = -expm1(log(0.05) / n)
    expected = -math.expm1(math.log(0.05) / n)
    assert clopper_pearson_upper(0, n) == pytest.approx(expected, rel=200 * EPS)


def test_known_values():
    assert clopper_pearson_upper(0, 1000) == pytest.approx(0.0029912, abs=5e-8)
    assert clopper_pearson_upper(0, 1) == pytest.approx(0.95, rel=1e-14)
    assert clopper_pearson_upper(3, 3) == 1.0
    assert clopper_pearson_upper(0, 1000) < 3 / 1000  # below the rule of three


def test_bound_is_monotone():
    n = 200
    ups = [clopper_pearson_upper(k, n) for k in range(n + 1)]
    assert all(a < b for a, b in zip(ups, ups[1:], strict=False))
    assert all(k / n <= u for k, u in enumerate(ups))


@pytest.mark.parametrize("args, err", [((-1, 10), ValueError), ((11, 10), ValueError),
                                       ((0, 0), ValueError), ((1.0, 10), TypeError),
                                       ((True, 10), TypeError), ((0, 10, 1.0), ValueError),
                                       ((0, 10, float("nan")), ValueError)])
def test_bad_input(args, err):
    with pytest.raises(err):
        clopper_pearson_upper(*args)


def test_pooled_quantiles_within_half_a_bin_of_the_order_statistic():
    rng = np.random.default_rng(1)
    chunks = [np.exp(rng.normal(np.log(50e-6), 0.6, size=rng.integers(200, 3000)))
              for _ in range(7)]
    pooled = np.sort(np.concatenate(chunks))
    hist = merge_histograms(time_histogram(c) for c in chunks)
    assert sum(c for _, c in hist) == pooled.size
    assert hist == time_histogram(pooled)  # merging equals binning everything at once
    for q in (0.0, 0.01, 0.5, 0.9, 0.99, 1.0):
        order_stat = pooled[max(1, math.ceil(q * pooled.size)) - 1]
        est = histogram_quantile(hist, q)
        assert abs(math.log10(est) - math.log10(order_stat)) <= 0.5 / BINS_PER_DECADE + 1e-12


def test_histogram_edge_cases():
    assert time_histogram([]) == [] and math.isnan(histogram_quantile([], 0.5))
    assert time_histogram([0.0, -1.0, float("nan"), float("inf")]) == []
    h = time_histogram([1e-4])
    assert histogram_quantile(h, 0.99) == pytest.approx(1e-4, rel=10 ** (0.5 / 50) - 1)
    with pytest.raises(ValueError):
        histogram_quantile(h, 1.5)
