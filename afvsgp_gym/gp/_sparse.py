"""Pieces shared by the sparse learners (VSGP, AFVSGP, SOGP): the inducing-point cache, greedy
inducing selection and the hyperparameter fit of the weighted collapsed bound (eqs. 21-23, 27).
"""

from __future__ import annotations

import numpy as np

from afvsgp_gym.gp._linalg import ubar
from afvsgp_gym.gp.bound import weighted_bound_and_grad
from afvsgp_gym.gp.hyper import LogNormalPrior, maximise, noise_box, theta_box
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["InducingCache", "fit_collapsed", "greedy_inducing", "pivoted_cholesky_select"]


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


SELECTION_TOL = 1e-6
"""Candidates whose residual prior variance is below this fraction of the largest prior variance
are never chosen as inducing points (guards against near-duplicate inducing inputs)."""


def pivoted_cholesky_select(diag: np.ndarray, column, num: int,
                            rel_tol: float = SELECTION_TOL) -> np.ndarray:
    """Greedy inducing-point selection (eq. 27 greedily): indices of up to ``num`` candidates,
    in the order chosen, each the one of largest residual prior variance given those before.

    ``diag`` (C,) are the candidates' prior variances, ``column(j)`` their covariances with
    candidate ``j`` (pivoted Cholesky with columns on demand, O(C num^2)); it greedily minimises
    ``tr(K_cc - Q_cc)``, the trace term of the collapsed bound. Stops early when every residual
    is below ``rel_tol`` times the largest prior variance, so duplicates are never chosen.
    """
    c = diag.shape[0]
    k_max = min(int(num), c)
    resid = diag.astype(np.float64, copy=True)
    tol = rel_tol * float(resid.max()) if c else 0.0
    rows = np.zeros((k_max, c))
    chosen: list[int] = []
    for k in range(k_max):
        j = int(np.argmax(resid))
        if not resid[j] > tol:
            break
        col = column(j) - rows[:k, j] @ rows[:k]
        col /= np.sqrt(resid[j])
        rows[k] = col
        resid -= col * col
        resid[j] = -np.inf
        chosen.append(j)
    return np.asarray(chosen, dtype=np.intp)


def greedy_inducing(kernel: ADPKernel, xi: np.ndarray, u: np.ndarray, num: int,
                    rel_tol: float = SELECTION_TOL) -> np.ndarray:
    """:func:`pivoted_cholesky_select` on the samples ``(xi, u)`` under ``kernel``."""
    ub = ubar(u)
    return pivoted_cholesky_select(
        kernel._diag(ub), lambda j: kernel._gram(xi, ub, xi[j:j + 1], ub[j:j + 1])[:, 0], num,
        rel_tol)


def _same_set(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether two inducing sets hold the same points (in any order)."""
    pa, pb = np.hstack(a), np.hstack(b)
    if pa.shape != pb.shape:
        return False
    return bool(np.array_equal(pa[np.lexsort(pa.T)], pb[np.lexsort(pb.T)]))


def fit_collapsed(kernel: ADPKernel, noise_variance: float, xi, u, z, weights, select, *,
                  jitter: float, maxiter: int, prior: LogNormalPrior | None, rounds: int = 3):
    """Maximise the weighted collapsed bound (eq. 23) plus the prior's log density over
    ``concat(theta, [log s2])`` (L-BFGS-B, analytic gradients, the jitter of
    :func:`~afvsgp_gym.gp._linalg.jitter_for` with factor ``jitter`` following the kernel).

    ``select(kernel) -> (xi_o, u_o)`` chooses the inducing set. After a fit the set is chosen
    again with the fitted kernel; if it changed, the fit is repeated on the new set (at most
    ``rounds`` fits). The result is therefore a stationary point on the set it returns (the
    last one fitted), never on a set chosen afterwards.

    Returns ``(kernel, noise_variance, (xi_o, u_o))``.
    """
    center = kernel.theta
    nl = kernel.n_components * kernel.input_dim
    bounds = theta_box(center) + [noise_box(z, weights)]
    work = kernel.clone()

    def evidence(p):
        val, grad = weighted_bound_and_grad(p, work, xi, u, z, weights, xo, uo, jitter,
                                            relative_jitter=True)
        if prior is not None:
            lp, glp = prior.log_density(p[:-1], center, nl)
            val += lp
            grad[:-1] += glp
        return val, grad

    params = np.concatenate([center, [np.log(noise_variance)]])
    xo, uo = select(kernel)
    for k in range(int(rounds)):
        params, _ = maximise(evidence, params, bounds, maxiter)
        kernel = kernel.with_theta(params[:-1])
        if k == rounds - 1:
            break
        nxt = select(kernel)
        if _same_set(nxt, (xo, uo)):
            break
        xo, uo = nxt
    return kernel, float(np.exp(params[-1])), (xo, uo)
