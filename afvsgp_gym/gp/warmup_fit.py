"""How the safety filter fits its learners at the end of warm-up (Algorithm 1, line 3).

- :func:`initial_kernel`: ADP kernel to start the bound maximisation from: one lengthscale
  for every feature and component (``sqrt(b)`` times the largest feature spread, so features
  that barely moved during warm-up are not made short-scaled), variances from
  ``ADPKernel.from_data``.
- :func:`fit_with_restarts`: one learner; L-BFGS-B on the collapsed bound sometimes stops at
  its initial point (a failed first line search), so it restarts from a smaller noise, doubled
  lengthscales and the learner's own data heuristic until the optimiser moves.
- :func:`fit_shared`: K learners (one per barrier) with one hyperparameter fit, on the
  barrier whose samples have the largest mean square. Each barrier's learner gets that
  kernel and noise rescaled to its own mean square (variances and noise times
  ``(rms_k / rms_ref)^2``: the same prior shape, the barrier's own output scale) with its own
  inducing set and posterior. The cost is one fit plus K posteriors instead of K fits.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["fit_shared", "fit_with_restarts", "initial_kernel"]

LearnerFactory = Callable[..., object]


def initial_kernel(xi: np.ndarray, u: np.ndarray, z: np.ndarray) -> ADPKernel:
    """Uniform-lengthscale ADP kernel for the start of the fit (see the module docstring)."""
    base = ADPKernel.from_data(xi, u, z)
    m1, b = u.shape[1] + 1, xi.shape[1]
    std = xi.std(axis=0) if len(xi) > 1 else np.ones(b)
    ls = float(np.sqrt(b) * np.max(std)) if np.max(std) > 1e-12 else 1.0
    return ADPKernel(np.full((m1, b), ls), base.variances)


def fit_with_restarts(make: LearnerFactory, xi, u, z, learn_hyperparameters: bool = True,
                      user_kernel: bool = False):
    """Fit ``make(**start)`` on ``(xi, u, z)``, restarting while L-BFGS-B does not move.

    ``make`` builds an unfitted learner from keyword overrides (``kernel``,
    ``noise_variance``). With ``user_kernel`` (the caller fixed the kernel) or without
    hyperparameter learning a single fit is made.
    """
    if not learn_hyperparameters or user_kernel:
        return make().fit(xi, u, z, learn_hyperparameters=learn_hyperparameters)
    k0 = initial_kernel(xi, u, z)
    vz = float(np.var(z)) if len(z) > 1 else 1.0
    starts = [
        {"kernel": k0},
        {"kernel": k0, "noise_variance": max(0.01 * vz, 1e-8)},
        {"kernel": ADPKernel(2.0 * k0.lengthscales, k0.variances)},
        {"kernel": None},
    ]
    best, best_bound = None, -np.inf
    for start in starts:
        learner = make(**start).fit(xi, u, z, learn_hyperparameters=True)
        k_start = start["kernel"]
        fitted = getattr(learner, "kernel_", None)
        if k_start is None or fitted is None or not np.allclose(fitted.theta, k_start.theta):
            return learner
        bound = float(getattr(learner, "bound_", None) or 0.0)
        if best is None or bound > best_bound:
            best, best_bound = learner, bound
    return best


def fit_shared(make: LearnerFactory, datasets: Sequence[tuple],
               learn_hyperparameters: bool = True, user_kernel: bool = False) -> list:
    """One learner per dataset ``(xi, u, z)`` with hyperparameters learned once, on the
    dataset with the largest mean square (see the module docstring)."""
    if len(datasets) == 1 or not learn_hyperparameters or user_kernel:
        return [fit_with_restarts(make, *d, learn_hyperparameters, user_kernel) for d in datasets]
    rms = np.array([np.sqrt(np.mean(d[2] ** 2)) if len(d[2]) else 0.0 for d in datasets])
    rms = np.where(rms > 1e-12, rms, 1.0)
    k_ref = int(np.argmax(rms))
    ref = fit_with_restarts(make, *datasets[k_ref], True)
    s = 1.0 / rms[k_ref] ** 2  # to unit rms, then each barrier's own below
    kernel = ADPKernel(ref.kernel_.lengthscales, ref.kernel_.variances * s)
    noise = float(ref.noise_variance_) * s
    out = []
    for (xi, u, z), s in zip(datasets, rms, strict=True):
        k = ADPKernel(kernel.lengthscales, kernel.variances * s * s)
        out.append(make(kernel=k, noise_variance=noise * s * s).fit(
            xi, u, z, learn_hyperparameters=False))
    return out
