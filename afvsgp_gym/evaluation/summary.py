"""The statistics of a set of episodes: :func:`summarize`."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

__all__ = ["SUMMARY_FIELDS", "summarize"]

#: Keys of one summary (:func:`summarize`), in table order.
SUMMARY_FIELDS = (
    "episodes",
    "episodes_with_cost",
    "cost_rate_upper",
    "episodes_with_violation",
    "episodes_with_contact",
    "episodes_with_limit_violation",
    "episodes_with_self_contact",
    "cost_steps",
    "violation_steps",
    "contact_steps",
    "limit_steps",
    "min_h",
    "interventions",
    "infeasible_steps",
    "learner_error_steps",
    "calibration_samples",
    "miss_rate",
    "near_miss_rate",
    "true_miss_rate",
    "coverage_1std",
    "coverage_2std",
    "coverage_3std",
    "tracking_error_mean",
    "tracking_error_max",
    "return_mean",
    "return_std",
    "steps",
    "unstable_episodes",
    "minimal_intervention",
    "filter_time_median_s",
    "filter_time_p99_s",
)


def _num(x: Any) -> float:
    return math.nan if x is None else float(x)


def summarize(records: Iterable[Mapping[str, Any]], confidence: float = 0.95) -> dict:
    """Aggregate episode records (of :func:`~afvsgp_gym.evaluation.run_spec` or
    ``evaluate`` rows).

    Counts are summed over episodes; ``episodes_with_cost`` is the headline with
    ``cost_rate_upper`` its exact one-sided Clopper-Pearson ``confidence`` bound;
    ``tracking_error_mean`` is the mean of the episode means (episodes without a counted step
    left out), ``min_h`` and ``tracking_error_max`` the extremes; ``minimal_intervention`` the
    share of the proposals that were safe with margin (true HOCBF constraint above
    :data:`~afvsgp_gym.episode_counts.SAFE_MARGIN` after warm-up) and passed the filter
    unchanged; ``miss_rate`` the share of the scored (barrier, step) pairs whose eq. 48 sample
    fell below the learned band the filter used (the chance constraint promises
    ``Phi(-beta)``), ``near_miss_rate`` the same over the pairs whose constraint was within
    one band-width of binding, ``true_miss_rate`` the same against the exact model error,
    ``coverage_1std`` (2, 3) the share within one (two, three) predicted standard deviations
    (NaN without scored pairs; :mod:`afvsgp_gym.cbf.calibration`); filter times are
    quantiles of every step pooled (from the records' histograms when present).
    """
    from afvsgp_gym.stats import clopper_pearson_upper, histogram_quantile, merge_histograms

    records = list(records)
    n = len(records)
    if n == 0:
        raise ValueError("summarize needs at least one episode record")
    returns = np.array([_num(r["return"]) for r in records])
    track = np.array([_num(r["tracking_error_mean"]) for r in records])
    track_max = np.array([_num(r["tracking_error_max"]) for r in records])
    with_cost = sum(int(r["cost_steps"]) > 0 for r in records)
    safe_total = sum(int(r.get("safe_proposals") or 0) for r in records)
    kept_total = sum(int(r.get("safe_proposals_kept") or 0) for r in records)
    hists = [r.get("filter_time_hist") for r in records]
    if all(h is not None for h in hists):
        hist = merge_histograms(hists)
        t_med, t_p99 = histogram_quantile(hist, 0.5), histogram_quantile(hist, 0.99)
    else:  # rows without histograms: episode quantiles only
        t_med = float(np.nanmedian([_num(r["filter_time_median_s"]) for r in records]))
        t_p99 = float(np.nanmax([_num(r["filter_time_p99_s"]) for r in records]))
    def total(name: str) -> int:  # (absent from the records of older sweeps: 0)
        return int(sum(int(r.get(name) or 0) for r in records))

    def rate(num: str, den: str) -> float:
        d = total(den)
        return total(num) / d if d else math.nan

    return {
        "episodes": n,
        "episodes_with_cost": int(with_cost),
        "cost_rate_upper": clopper_pearson_upper(int(with_cost), n, confidence),
        "episodes_with_violation": int(sum(int(r["violation_steps"]) > 0 for r in records)),
        "episodes_with_contact": int(sum(int(r["contact_steps"]) > 0 for r in records)),
        "episodes_with_limit_violation": int(sum(int(r.get("limit_steps") or 0) > 0
                                                 for r in records)),
        # (absent from the records of older sweeps: not counted then)
        "episodes_with_self_contact": int(sum(int(r.get("self_contact_steps") or 0) > 0
                                              for r in records)),
        "cost_steps": int(sum(int(r["cost_steps"]) for r in records)),
        "violation_steps": int(sum(int(r["violation_steps"]) for r in records)),
        "contact_steps": int(sum(int(r["contact_steps"]) for r in records)),
        "limit_steps": int(sum(int(r.get("limit_steps") or 0) for r in records)),
        "min_h": float(min(_num(r["min_h"]) for r in records)),
        "interventions": int(sum(int(r["interventions"]) for r in records)),
        "infeasible_steps": int(sum(int(r["infeasible_steps"]) for r in records)),
        # (absent from the records of older sweeps: none counted then)
        "learner_error_steps": int(sum(int(r.get("learner_error_steps") or 0)
                                       for r in records)),
        "calibration_samples": total("calibration_samples"),
        "miss_rate": rate("calibration_misses", "calibration_samples"),
        "near_miss_rate": rate("calibration_near_misses", "calibration_near_samples"),
        "true_miss_rate": rate("true_band_misses", "true_band_samples"),
        "coverage_1std": rate("calibration_within_1std", "calibration_samples"),
        "coverage_2std": rate("calibration_within_2std", "calibration_samples"),
        "coverage_3std": rate("calibration_within_3std", "calibration_samples"),
        "tracking_error_mean": float(np.mean(track[np.isfinite(track)]))
        if np.isfinite(track).any() else math.nan,
        "tracking_error_max": float(np.max(track_max[np.isfinite(track_max)]))
        if np.isfinite(track_max).any() else math.nan,
        "return_mean": float(returns.mean()),
        "return_std": float(returns.std()),
        "steps": int(sum(int(r["steps"]) for r in records)),
        "unstable_episodes": int(sum(bool(r["unstable"]) for r in records)),
        "minimal_intervention": (kept_total / safe_total) if safe_total else math.nan,
        "filter_time_median_s": t_med,
        "filter_time_p99_s": t_p99,
    }
