"""Calibration of the learned band of the chance constraint (eq. 49 with a constant
multiplier): what it promised, what the eq. 48 samples showed, and an online conformal
correction of the multiplier.

The cone program asks, per barrier ``k`` in the program, that the learned constraint hold at
the band's lower edge ``lower_k = mean_k + bias_k - q_k std_k`` (``std_k`` the predicted
standard deviation of ``Delta B_k`` at the applied action, eq. 51, ``bias_k`` the residual
observer's correction, ``q_k = beta`` unless corrected). The promise is that the model error
falls below that edge with probability ``alpha = Phi(-beta)`` (0.62 % at ``beta = 2.5``).
After the step, the eq. 48 sample ``z_k`` gives the score ``e_k = (z_k - mean_k - bias_k) /
std_k``: a *miss* is ``e_k < -q_k``, and ``|e_k| <= 1, 2, 3`` are the two-sided coverages of
one, two and three standard deviations (68.3, 95.4, 99.7 % for a calibrated Gaussian).

:class:`ConformalMultiplier` adapts the band online by quantile tracking (adaptive conformal
inference, Gibbs and Candes 2021; the P term of conformal PID control, Angelopoulos et al.
2023), per learner (a joint's four limit barriers share their learner's), in one of two ways:

- ``"conformal"``, the multiplier: ``q <- max(beta, q + eta * sum_k (miss_k - alpha))``, the
  band ``mean + bias - q std``;
- ``"conformal-additive"``, a margin in the model error's own unit: the band
  ``mean + bias - beta std - m`` with ``m <- max(0, m + eta sigma * sum_k (miss_k - alpha))``,
  ``sigma`` the learner's noise standard deviation. Where the model is confident and wrong
  (a small ``std``) a multiplier must grow large, and then also widens the band where the
  model is uncertain; a margin does not.

A learner's barriers may mix the two (``additive`` per barrier): its multiplier adapts from
the scores of its multiplier barriers only, its margin from those of its margin barriers, and
the guarantee below holds for each of the two sets apart.

**Guarantee** (deterministic, for any sequence of states, actions and model errors, however
misspecified the GP): if every score of a learner's barriers satisfies ``e_k >= -Q``, then
over its first ``N`` scored samples the misses number at most
``alpha N + (Q - beta + eta n) / eta`` (``n`` the most samples of one step, 4 for a joint), so
the one-sided miss rate is at most ``alpha + (Q - beta + eta n) / (eta N)``. Proof: the floor
only adds to ``q``, so ``eta (misses - alpha N) <= q_N - beta``, and ``q`` rises only after a
miss, which needs ``q < Q``. For the margin, the same with ``Q`` the largest
``(mean + bias - beta std - z) / sigma`` and ``beta`` replaced by 0. The assumptions: the
scores are finite (a sample that is not is skipped) and each is revealed before the next
step's update (eq. 48's one-step delay). It is a long-run rate, not a per-step probability,
and it covers the eq. 48 sample (the true model error plus the measurement's own error), not
the true model error alone. The floor at ``beta`` (at 0 for the margin) means a
well-specified model is barely widened: its misses arrive at rate ``alpha``, and the band
returns to the paper's between them.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = ["CALIBRATION_MODES", "CalibrationCounts", "ConformalMultiplier",
           "beta_for_miss_probability", "miss_target", "score_counts", "scores"]

#: Values of ``FilterConfig.calibration``.
CALIBRATION_MODES = ("off", "conformal", "conformal-additive")


def miss_target(beta: float) -> float:
    """``alpha = Phi(-beta)``: the one-sided miss probability the band promises (eq. 49)."""
    return 0.5 * math.erfc(float(beta) / math.sqrt(2.0))


def beta_for_miss_probability(miss_probability: float) -> float:
    """``beta = Phi^-1(1 - p)``: the multiplier whose band promises the one-sided miss
    probability ``p`` (the inverse of :func:`miss_target`; ``p = 0.5`` gives ``beta = 0``,
    the mean-only program). ``ValueError`` naming ``miss_probability`` outside (0, 0.5].

    Example:
        >>> round(beta_for_miss_probability(0.0062097), 4)
        2.5
    """
    from statistics import NormalDist

    try:
        p = float(miss_probability)
    except (TypeError, ValueError):
        raise ValueError(f"miss_probability must be a number in (0, 0.5]. "
                         f"Got: {miss_probability!r}") from None
    if not 0.0 < p <= 0.5:
        raise ValueError(f"miss_probability must be in (0, 0.5]. Got: {miss_probability!r}")
    return max(0.0, -NormalDist().inv_cdf(p))


class CalibrationCounts(NamedTuple):
    """The calibration of one step's band, over the barriers the filter predicted.

    Attributes
    ----------
    samples : int
        Barriers with a finite score ``e_k``.
    misses : int
        Those below the band the filter used (``z_k`` below its lower edge).
    within_1std, within_2std, within_3std : int
        Those with ``|e_k| <= 1, 2, 3`` (two-sided coverage of the predicted std).
    near_samples, near_misses : int
        The scored barriers whose constraint was near binding (its margin at the applied
        action below the band's width, ``center - lower``: one band-width more model error
        would have violated it), and their misses: the subsequence ``calibration_gate``
        corrects on, where the band decides the action (0 when not told).
    """

    samples: int
    misses: int
    within_1std: int
    within_2std: int
    within_3std: int
    near_samples: int = 0
    near_misses: int = 0

    def as_dict(self) -> dict[str, int]:
        """The counts as the dict ``info["calibration"]`` holds."""
        return self._asdict()


def scores(z: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """``e = (z - mean) / std``, NaN where any input is not finite or ``std <= 0``."""
    d = np.asarray(z, dtype=np.float64) - mean
    if (std > 0).all():
        e = d / std
        if np.isfinite(e).all():
            return e
    with np.errstate(divide="ignore", invalid="ignore"):
        e = d / std
    return np.where(np.isfinite(e) & (std > 0), e, np.nan)


def near_binding(margin: np.ndarray, center: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """Constraints within one band-width of binding: ``margin < center - lower`` (their
    margin at the applied action below the band's width; NaN margins are not)."""
    with np.errstate(invalid="ignore"):
        return np.asarray(margin) < center - lower


def score_counts(z: np.ndarray, mean: np.ndarray, std: np.ndarray, lower: np.ndarray,
                 near: np.ndarray | None = None) -> tuple[np.ndarray, CalibrationCounts]:
    """:func:`scores` and their :class:`CalibrationCounts` (``mean`` includes the residual
    bias; a miss is a scored ``z < lower``, the band's lower edge; ``near`` (k,) bool the
    near-binding rows, :func:`near_binding`)."""
    e = scores(z, mean, std)
    ok = ~np.isnan(e)
    z = np.asarray(z)
    miss = z < lower
    a = np.abs(e[ok])
    n_near = n_near_miss = 0
    if near is not None:
        near_ok = near & ok
        n_near = int(np.count_nonzero(near_ok))
        n_near_miss = int(np.count_nonzero(near_ok & miss))
    counts = CalibrationCounts(int(np.count_nonzero(ok)), int(np.count_nonzero(ok & miss)),
                               int(np.count_nonzero(a <= 1.0)),
                               int(np.count_nonzero(a <= 2.0)),
                               int(np.count_nonzero(a <= 3.0)), n_near, n_near_miss)
    return e, counts


class ConformalMultiplier:
    """Online quantile tracking of the band, one multiplier (or margin) per learner (module
    docstring).

    Parameters
    ----------
    groups : ndarray of int, shape (K,)
        The multiplier barrier ``k`` uses (its learner's number).
    beta : float
        The configured multiplier: the floor and the start, and ``alpha = Phi(-beta)`` the
        target miss rate.
    step : float or array_like of shape (K,)
        ``eta``, standard deviations per miss (a miss raises ``q`` by ``eta (1 - alpha)``,
        a sample inside the band lowers it by ``eta alpha``); for the margin, noise standard
        deviations per miss. Per barrier: each learner takes the largest of its barriers'
        (0: that learner's band stays the paper's).
    additive : bool or array_like of bool, shape (K,)
        Adapt the margin ``m`` (``margin``, from 0) instead of the multiplier ``q`` (which
        stays ``beta``), for all barriers or per barrier: a learner's multiplier adapts from
        its multiplier barriers' scores, its margin from its margin barriers'.

    Example:
        >>> import numpy as np
        >>> cm = ConformalMultiplier(np.array([0, 0, 1]), beta=2.5, step=0.5)
        >>> cm.update(np.array([0, 2]), np.array([-4.0, 0.3]))  # barrier 0 missed
        >>> cm.multiplier(np.array([0, 1, 2])).round(3)
        array([2.997, 2.997, 2.5  ])
    """

    def __init__(self, groups: np.ndarray, beta: float, step, additive=False):
        self.groups = np.asarray(groups, dtype=np.intp)
        self.beta = float(beta)
        #: (K,) whether each barrier's band takes the margin (else the multiplier)
        self.additive = np.broadcast_to(np.asarray(additive, dtype=bool),
                                        self.groups.shape).copy()
        #: whether some band takes a multiplier / a margin
        self.any_multiplier = bool((~self.additive).any())
        self.any_margin = bool(self.additive.any())
        self.target = miss_target(beta)
        n = int(self.groups.max()) + 1 if self.groups.size else 0
        per_barrier = np.broadcast_to(np.asarray(step, dtype=np.float64), self.groups.shape)
        #: (L,) each learner's step: the largest of its barriers'
        self.step = np.zeros(n)
        np.maximum.at(self.step, self.groups, per_barrier)
        self.q = np.full(n, self.beta)
        #: the additive margins (0 for the multiplier), in each learner's model-error unit
        self.margin = np.zeros(n)
        #: each learner's unit of the margin's step (its noise std, set at its first update)
        self.unit = np.full(n, np.nan)

    def multiplier(self, rows: np.ndarray) -> np.ndarray:
        """The multipliers of barriers ``rows`` (a copy; ``beta`` for the margin's)."""
        q = self.q[self.groups[rows]]
        return np.where(self.additive[rows], self.beta, q) if self.any_margin else q

    def margins(self, rows: np.ndarray) -> np.ndarray:
        """The additive margins of barriers ``rows`` (a copy; zeros for the multiplier's)."""
        m = self.margin[self.groups[rows]]
        return np.where(self.additive[rows], m, 0.0) if self.any_multiplier else m

    def update(self, rows: np.ndarray, scores: np.ndarray, std: np.ndarray | None = None,
               noise_std: np.ndarray | None = None) -> None:
        """One step's scores of barriers ``rows`` (NaN skipped), each judged against the band
        the filter used, i.e. the current one; the margin also needs the scores' ``std`` and
        the learners' ``noise_std`` (per row)."""
        ok = ~np.isnan(scores)
        if not ok.any():
            return
        if self.any_multiplier:
            mult = ok & ~self.additive[rows]
            if mult.any():
                g = self.groups[rows[mult]]
                miss = scores[mult] < -self.q[g]
                np.add.at(self.q, g, self.step[g] * (miss - self.target))
                np.maximum(self.q, self.beta, out=self.q)
        if self.any_margin:
            marg = ok & self.additive[rows]
            if marg.any():
                self._update_margin(rows[marg], scores[marg], std[marg], noise_std[marg])

    def _update_margin(self, rows, scores, std, noise_std) -> None:
        g = self.groups[rows]
        unset = np.isnan(self.unit[g])
        if unset.any():
            self.unit[g[unset]] = noise_std[unset]
        # below mean + bias - beta std - m, in the model error's unit
        miss = scores * std < -self.beta * std - self.margin[g]
        np.add.at(self.margin, g, self.step[g] * self.unit[g] * (miss - self.target))
        np.maximum(self.margin, 0.0, out=self.margin)
