"""Statistics of safety evidence over seeded episodes.

- :func:`clopper_pearson_upper`: the exact one-sided upper confidence bound on a per-episode
  event rate (episodes with cost) after ``k`` events in ``n`` independent episodes.
- :func:`time_histogram` / :func:`histogram_quantile`: per-step filter times kept as counts in
  log-spaced bins (``BINS_PER_DECADE`` per decade), so quantiles pooled over thousands of
  episodes need no raw times; a pooled quantile is the geometric centre of the bin holding the
  order statistic, within a factor ``10 ** (1 / (2 * BINS_PER_DECADE))`` (2.3 %) of it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

__all__ = [
    "BINS_PER_DECADE",
    "clopper_pearson_upper",
    "histogram_quantile",
    "merge_histograms",
    "time_histogram",
]

BINS_PER_DECADE = 50


def clopper_pearson_upper(k: int, n: int, confidence: float = 0.95) -> float:
    """Exact one-sided upper ``confidence`` bound on a binomial rate after ``k`` events in ``n``.

    The bound ``p_u`` solves ``P[Binomial(n, p_u) <= k] = 1 - confidence``, i.e.
    ``p_u = BetaInv(confidence; k + 1, n - k)`` (Clopper and Pearson, 1934), and is 1 when
    ``k = n``. With ``k = 0`` it is ``1 - (1 - confidence) ** (1 / n)`` (about ``3 / n`` at 95 %,
    the rule of three): 0 of 1000 episodes bounds the rate below 0.299 %.
    """
    from scipy.stats import beta

    for name, v in (("k", k), ("n", n)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer):
            raise TypeError(f"{name} must be an integer, got {v!r}")
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if not 0 <= k <= n:
        raise ValueError(f"k must be in [0, n] = [0, {n}], got {k}")
    if not (isinstance(confidence, float | int) and 0.0 < confidence < 1.0):
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    if k == n:
        return 1.0
    return float(beta.ppf(confidence, k + 1, n - k))


def time_histogram(times: Iterable[float]) -> list[list[int]]:
    """Sparse histogram ``[[bin, count], ...]`` (ascending bins) of positive times in seconds.

    Bin ``j`` holds ``[10 ** (j / B), 10 ** ((j + 1) / B))`` with ``B = BINS_PER_DECADE``;
    non-finite or non-positive times are dropped (a filter time is always positive).
    """
    arr = np.asarray(list(times), dtype=float)
    arr = arr[np.isfinite(arr) & (arr > 0)]
    if arr.size == 0:
        return []
    idx = np.floor(np.log10(arr) * BINS_PER_DECADE).astype(np.int64)
    bins, counts = np.unique(idx, return_counts=True)
    return [[int(b), int(c)] for b, c in zip(bins, counts, strict=True)]


def merge_histograms(histograms: Iterable[Sequence[Sequence[int]]]) -> list[list[int]]:
    """Sum sparse histograms of :func:`time_histogram` into one."""
    total: dict[int, int] = {}
    for hist in histograms:
        for b, c in hist or ():
            total[int(b)] = total.get(int(b), 0) + int(c)
    return [[b, total[b]] for b in sorted(total)]


def histogram_quantile(hist: Sequence[Sequence[int]], q: float) -> float:
    """Quantile ``q`` in [0, 1] of the times in a sparse histogram; NaN when it is empty.

    Returns the geometric centre of the bin holding the order statistic of rank
    ``ceil(q * N)`` (1-based, at least 1), so the result is within a factor
    ``10 ** (1 / (2 B))`` of that order statistic.
    """
    if not 0.0 <= q <= 1.0:
        raise ValueError(f"q must be in [0, 1], got {q}")
    n = sum(int(c) for _, c in hist)
    if n == 0:
        return math.nan
    rank = max(1, math.ceil(q * n))
    seen = 0
    for b, c in sorted((int(b), int(c)) for b, c in hist):
        seen += c
        if seen >= rank:
            return 10.0 ** ((b + 0.5) / BINS_PER_DECADE)
    raise AssertionError("unreachable: rank <= n")  # pragma: no cover
