"""Hyperparameter fit shared by the learners: the weak prior, the search box and the one L-BFGS-B
wrapper (type-II maximum a posteriori of ``concat(kernel.theta, [log s2])``).

The objective is a log evidence (the collapsed bound of eq. 23 for the sparse learners, the log
marginal likelihood for the exact GP) plus :class:`LogNormalPrior`'s log density. The prior is
centred at the initial kernel (the caller's, or ``ADPKernel.from_data``): parameters the data
determine stay where the data put them, while the flat directions of the evidence (a lengthscale
far beyond the data's extent, a variance traded against a lengthscale) are held near the initial
scale instead of drifting to the edge of the box. Choice and evidence: docs/learners.md,
"The hyperparameter fit".
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

__all__ = ["DEFAULT_PRIOR", "LogNormalPrior", "maximise", "noise_box", "theta_box"]

#: Half-width (in log units) of the search box around the initial log parameters.
THETA_BOX = 8.0

#: The noise variance is searched in ``[NOISE_MIN, NOISE_MAX] * mean(lambda z^2)``. The floor
#: is GPyTorch's default lower bound on the likelihood noise (1e-4, there on standardised
#: targets): simulated measurements are nearly noise-free, the evidence then drives the noise
#: to the floor, and a floor of 1e-6 let the posterior nearly interpolate and extrapolate
#: wildly after an inducing-point swap (docs/learners.md, "The hyperparameter fit").
NOISE_MIN, NOISE_MAX = 1e-4, 10.0 * np.e

#: L-BFGS-B stops when an iteration improves the objective by less than this fraction.
FTOL = 1e-12

#: Objective value reported to L-BFGS-B where the evidence cannot be evaluated (a failed
#: Cholesky or a non-finite value while exploring): far worse than any evidence, so the line
#: search backs off, yet finite so its interpolation stays finite.
_FAILED = 1e25


@dataclass(frozen=True)
class LogNormalPrior:
    """Independent normal priors on the log lengthscales and log variances of the ADP kernel,
    centred at the initial kernel's: ``log l ~ N(log l_0, lengthscale_std^2)``,
    ``log s_i ~ N(log s_i0, variance_std^2)``; the noise variance has none (it is bounded by
    :func:`noise_box`). ``std = inf`` switches a prior off."""

    lengthscale_std: float = 1.5
    variance_std: float = 1.5

    def __post_init__(self):
        for name in ("lengthscale_std", "variance_std"):
            val = getattr(self, name)
            if not (isinstance(val, int | float) and val > 0):
                raise ValueError(f"{name} must be a positive number (inf: no prior), got {val!r}")

    def log_density(self, theta: np.ndarray, center: np.ndarray, n_lengthscales: int):
        """Log density (up to a constant) and its gradient at ``theta`` (kernel parameters)."""
        std = np.empty_like(theta)
        std[:n_lengthscales] = self.lengthscale_std
        std[n_lengthscales:] = self.variance_std
        dev = (theta - center) / std
        return -0.5 * float(dev @ dev), -dev / std


#: The prior every learner uses unless told otherwise (``prior=None`` fits without one); the
#: choice of 1.5 for both standard deviations, against none, variances only, 1.0 and 3.0, is in
#: docs/learners.md ("The hyperparameter fit").
DEFAULT_PRIOR = LogNormalPrior()


def theta_box(theta0: np.ndarray) -> list[tuple[float, float]]:
    """Box of the kernel's log parameters: ``theta0 +- THETA_BOX``."""
    return [(t - THETA_BOX, t + THETA_BOX) for t in theta0]


def noise_box(z: np.ndarray, weights: np.ndarray | None = None) -> tuple[float, float]:
    """Box of ``log s2`` from the data's scale ``mean(lambda z^2)``."""
    scale = max(float(np.average(z * z, weights=weights)), 1e-12)
    return float(np.log(max(NOISE_MIN * scale, 1e-12))), float(np.log(NOISE_MAX * scale))


def maximise(evidence: Callable[[np.ndarray], tuple[float, np.ndarray]], x0: np.ndarray,
             bounds: list[tuple[float, float]], maxiter: int) -> tuple[np.ndarray, float]:
    """Maximise ``evidence(x) -> (value, gradient)`` with L-BFGS-B from ``x0`` (clipped into
    ``bounds``). Evaluations that raise ``LinAlgError`` or are not finite count as
    :data:`_FAILED`. Returns ``(x, value)``; ``x0`` if nothing better was found."""
    lo = np.array([b[0] for b in bounds])
    hi = np.array([b[1] for b in bounds])
    x0 = np.clip(np.asarray(x0, dtype=float), lo, hi)

    def negative(x):
        try:
            with warnings.catch_warnings():  # jitter retries while exploring are expected
                warnings.simplefilter("ignore", RuntimeWarning)
                val, grad = evidence(x)
        except np.linalg.LinAlgError:
            return _FAILED, np.zeros_like(x)
        if not (np.isfinite(val) and np.all(np.isfinite(grad))):
            return _FAILED, np.zeros_like(x)
        return -val, -grad

    f0 = negative(x0)[0]
    res = minimize(negative, x0, jac=True, method="L-BFGS-B", bounds=bounds,
                   options={"maxiter": int(maxiter), "ftol": FTOL})
    if np.isfinite(res.fun) and res.fun < _FAILED and res.fun <= f0:
        return res.x, -float(res.fun)
    return x0, -float(f0)
