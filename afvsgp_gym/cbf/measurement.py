"""Measurement of the HOCBF model error (paper eq. 48).

The learned quantity is ``Delta B^(r)(xi, ubar) = B^(r) - B0^(r)`` (eq. 46). The terms
``S + alpha_r(psi_{r-1})`` are computed from measured derivatives and are identical in the true
and nominal models, so ``Delta B^(r) = h^(r)_true - h^(r)_nominal``. Eq. 48 is then

    z = (h^(r-1)(t + dt) - h^(r-1)(t)) / dt  -  (lf0 + lg0 @ u)_mid,

the finite difference of the highest measured derivative over the control period minus the
nominal ``h^(r)`` for the applied action at the midpoint, taken as the average of the nominal
terms before and after the step (trapezoid rule: second-order accurate for smooth motion). The
feature of the sample is the midpoint ``xi_j = (xi(t) + xi(t + dt)) / 2``.
"""

from __future__ import annotations

import math

import numpy as np

from afvsgp_gym import _compiled
from afvsgp_gym.types import BarrierSet, BarrierTerms

_step = _compiled.extension("step")


def nominal_highest_derivative(terms: BarrierTerms, u: np.ndarray) -> float:
    """``h^(r)`` of the model in ``terms`` for action ``u`` (eq. 45 without S and alpha)."""
    return float(terms.lf) + float(np.asarray(terms.lg, dtype=np.float64) @ u)


def measure(
    terms_before: BarrierTerms, u: np.ndarray, terms_after: BarrierTerms, dt: float
) -> tuple[np.ndarray, float]:
    """One eq. 48 sample ``(xi_j, z_j)`` for the action ``u`` applied during ``dt``.

    Returns NaN in ``z`` when any input is not finite (the caller skips such samples).
    """
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be finite and positive. Got: {dt!r}")
    u = np.asarray(u, dtype=np.float64)
    r = terms_before.relative_degree
    fd = (float(terms_after.derivatives[r - 1]) - float(terms_before.derivatives[r - 1])) / dt
    nominal = 0.5 * (
        nominal_highest_derivative(terms_before, u) + nominal_highest_derivative(terms_after, u)
    )
    xi = 0.5 * (np.asarray(terms_before.xi, np.float64) + np.asarray(terms_after.xi, np.float64))
    return xi, fd - nominal


def measure_all(
    before: BarrierSet, u: np.ndarray, after: BarrierSet, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """The eq. 48 samples of K barriers at once: ``xi_j`` (K, b) and ``z_j`` (K,).

    NaN in ``z`` for barriers whose inputs are not finite (the learners skip them).
    """
    xi, z, _ = measure_samples(before, u, after, dt)
    return xi, z


def measure_samples(
    before: BarrierSet, u: np.ndarray, after: BarrierSet, dt: float,
    degrees: np.ndarray | None = None,
    backend: str | _compiled.Backend = "auto",
) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`measure_all` and the number of samples whose ``z`` or ``xi`` is not finite (the
    elementwise part in the compiled step glue unless ``backend`` is ``"numpy"``: the same
    digits). ``degrees`` (K,): each barrier's relative degree when they differ (the finite
    difference of its own highest measured derivative, column ``r_k - 1``); None: the terms'
    own."""
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be finite and positive. Got: {dt!r}")
    u = np.asarray(u, dtype=np.float64)
    r = before.relative_degree
    lgu_before, lgu_after = before.lg @ u, after.lg @ u
    xi, z, bad = _samples(before, lgu_before, after, lgu_after, dt, r, backend)
    if degrees is not None:  # the barriers of lower degree: their own highest derivative
        low = np.flatnonzero(degrees != r)
        if len(low):
            col = degrees[low] - 1
            fd = (after.derivatives[low, col] - before.derivatives[low, col]) / dt
            nominal = 0.5 * ((before.lf[low] + lgu_before[low]) + (after.lf[low] + lgu_after[low]))
            z[low] = fd - nominal
            if bad or not math.isfinite(float(z[low].sum())):
                bad = int((~(np.isfinite(z) & np.all(np.isfinite(xi), axis=1))).sum())
    return xi, z, bad


def _samples(before: BarrierSet, lgu_before: np.ndarray, after: BarrierSet,
             lgu_after: np.ndarray, dt: float, r: int, backend) -> tuple[np.ndarray, np.ndarray,
                                                                       int]:
    """Eq. 48 on column ``r - 1`` of every barrier, and the count of non-finite samples."""
    if _compiled.resolve(backend, ("step",)).step:
        K, nb = before.xi.shape
        xi, z = np.empty((K, nb)), np.empty(K)
        try:
            bad = _step.measure(K, r, nb, float(dt), before.lf, lgu_before, before.derivatives,
                                before.xi, after.lf, lgu_after, after.derivatives, after.xi,
                                xi, z)
        except ValueError:  # arrays the core does not take (not float64, C-ordered, equal)
            pass
        else:
            return xi, z, bad
    fd = (after.derivatives[:, r - 1] - before.derivatives[:, r - 1]) / dt
    nominal = 0.5 * ((before.lf + lgu_before) + (after.lf + lgu_after))
    xi, z = 0.5 * (before.xi + after.xi), fd - nominal
    if math.isfinite(float(z.sum()) + float(xi.sum())):  # a finite sum: every value is
        return xi, z, 0
    return xi, z, int((~(np.isfinite(z) & np.all(np.isfinite(xi), axis=1))).sum())
