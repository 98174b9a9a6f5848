"""Pieces shared by the sparse learners (VSGP, AFVSGP): inducing-point cache, greedy
selection, hyperparameter fit of the weighted bound, and the affine predictive (eqs. 20-22).
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.optimize import minimize

from afvsgp_gym.gp._linalg import ubar
from afvsgp_gym.gp.bound import weighted_bound_and_grad
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["InducingCache", "affine_from_kt", "fit_bound", "greedy_inducing"]


class InducingCache:
    """Inducing inputs in preallocated buffers with per-component scaled copies.

    ``kt(xi)`` returns ``Kt[i, j] = k_i(xi, o_j) ubar_{o_j, i}`` (m+1, M) for one point, the
    matrix of paper eq. 21, with no Python loop over inducing points.
    """

    def __init__(self, kernel: ADPKernel, capacity: int):
        self.kernel = kernel
        self.cap = capacity
        self.M = 0
        b, c = kernel.input_dim, kernel.n_components
        self.xi = np.zeros((capacity, b))
        self.ub = np.zeros((capacity, c))
        self.ubt = np.zeros((c, capacity))  # ub transposed
        # rows [xi_o / l_i^2, -1 / (2 l_i^2), log s_i - |xi_o / l_i|^2 / 2] per (i, o)
        self.xs2 = np.zeros((c, capacity, 2 * b + 1))
        self._a = self.xs2.reshape(c * capacity, 2 * b + 1)  # a view
        self.inv_ls2 = kernel._inv_ls ** 2
        self.var = kernel._var
        self.var_diag = np.diag(kernel._var)
        self.log_var = np.log(kernel._var)
        self._v = np.ones(2 * b + 1)  # [xi, xi^2, 1]

    def set(self, xi: np.ndarray, ub: np.ndarray) -> None:
        n = xi.shape[0]
        if n > self.cap:
            raise ValueError(f"too many inducing points ({n} > capacity {self.cap})")
        self.M = 0
        for j in range(n):
            self.append(xi[j], ub[j])

    def append(self, xi: np.ndarray, ub: np.ndarray) -> None:
        j = self.M
        self.xi[j] = xi
        self.ub[j] = ub
        self.ubt[:, j] = ub
        s = xi[None, :] * self.inv_ls2
        b = xi.shape[0]
        self.xs2[:, j, :b] = s
        self.xs2[:, j, b:2 * b] = -0.5 * self.inv_ls2
        self.xs2[:, j, 2 * b] = self.log_var - 0.5 * (s @ xi)
        self.M = j + 1

    def delete(self, j: int) -> None:
        m = self.M
        for arr in (self.xi, self.ub):
            arr[j:m - 1] = arr[j + 1:m]
        for arr in (self.ubt, self.xs2):
            arr[:, j:m - 1] = arr[:, j + 1:m]
        self.M = m - 1

    def kt(self, xi: np.ndarray) -> np.ndarray:
        """(m+1, M) per-component cross covariance of one point (eq. 21).

        ``log k_i(xi, o_j) = log s_i - |xi/l_i|^2/2 + (o_j/l_i^2).xi - |o_j/l_i|^2/2``: one
        matrix-vector product (with ``[xi, xi^2, 1]``) for all components and inducing points.
        """
        c, cap, b2 = self.xs2.shape
        v = self._v
        b = b2 // 2
        v[:b] = xi
        np.multiply(xi, xi, out=v[b:2 * b])
        e = (self._a @ v).reshape(c, cap)
        np.exp(e, out=e)
        e *= self.ubt
        return e[:, : self.M]

    def kt_batch(self, xi: np.ndarray) -> np.ndarray:
        """(N, m+1, M) per-component cross covariance of N points."""
        m = self.M
        return self.kernel._cross_affine(xi, self.xi[:m], self.ub[:m])


def affine_from_kt(kt: np.ndarray, var: np.ndarray, w: np.ndarray, d: np.ndarray):
    """Affine predictive (eq. 20) from ``Kt`` (N, m+1, M): ``b = Kt w``,
    ``Sigma = diag(var) - Kt D Kt'`` with ``D = K_oo^-1 - B`` (symmetrised)."""
    b = kt @ w
    sig = -np.matmul(kt @ d, kt.transpose(0, 2, 1))
    sig = 0.5 * (sig + sig.transpose(0, 2, 1))
    idx = np.arange(var.shape[0])
    sig[:, idx, idx] += var
    return b, sig


def greedy_inducing(kernel: ADPKernel, xi: np.ndarray, u: np.ndarray, num: int,
                    rel_tol: float = 1e-6) -> np.ndarray:
    """Indices of up to ``num`` inducing points by pivoted Cholesky of the ADP gram
    (largest residual prior variance first, i.e. eq. 27 greedily); O(N num^2).
    Stops early when every residual is below ``rel_tol`` times the largest prior variance,
    so duplicates are never chosen."""
    ub = ubar(u)
    n = xi.shape[0]
    resid = kernel._diag(ub).copy()
    tol = rel_tol * float(resid.max())
    rows = np.zeros((min(num, n), n))
    chosen: list[int] = []
    for k in range(min(num, n)):
        j = int(np.argmax(resid))
        if resid[j] <= tol:
            break
        col = kernel._gram(xi, ub, xi[j:j + 1], ub[j:j + 1])[:, 0]
        col -= rows[:k].T @ rows[:k, j]
        col /= np.sqrt(resid[j])
        rows[k] = col
        resid -= col * col
        resid[j] = -np.inf
        chosen.append(j)
    return np.asarray(chosen, dtype=int)


def fit_bound(kernel: ADPKernel, noise_variance: float, xi, u, z, weights, xi_o, u_o,
              jitter: float, maxiter: int = 200, min_noise: float = 1e-6):
    """Maximise the weighted collapsed bound (eq. 23) over kernel theta and log noise with
    L-BFGS-B (analytic gradients). Returns (kernel, noise_variance, bound value)."""
    work = kernel.clone()
    x0 = np.concatenate([kernel.theta, [np.log(noise_variance)]])
    scale = max(float(np.average(z * z, weights=weights)), 1e-12)
    lo_noise = np.log(max(min_noise * scale, 1e-12))
    bounds = [(t - 8.0, t + 8.0) for t in x0[:-1]] + [(lo_noise, np.log(10.0 * scale) + 1.0)]
    x0[-1] = np.clip(x0[-1], bounds[-1][0], bounds[-1][1])

    def fun(p):
        try:
            with warnings.catch_warnings():  # jitter retries while exploring are expected
                warnings.simplefilter("ignore", RuntimeWarning)
                val, grad = weighted_bound_and_grad(p, work, xi, u, z, weights, xi_o, u_o,
                                                    jitter)
        except np.linalg.LinAlgError:
            return 1e300, np.zeros_like(p)
        if not np.isfinite(val) or not np.all(np.isfinite(grad)):
            return 1e300, np.zeros_like(p)
        return -val, -grad

    res = minimize(fun, x0, jac=True, method="L-BFGS-B", bounds=bounds,
                   options={"maxiter": maxiter})
    best = res.x if res.fun <= fun(x0)[0] else x0
    return kernel.with_theta(best[:-1]), float(np.exp(best[-1])), -float(fun(best)[0])
