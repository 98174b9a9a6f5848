"""Scale-aware tolerances for the GP tests, from the conditioning of what is compared.

Two float64 computations of the same quantity differ by rounding. Each tolerance here is a
first-order bound: the backward error of the computation (Higham's ``gamma(n) = n u / (1 - n u)``,
``u = EPS / 2``, times the magnitudes entering a sum or a factorisation) pushed through the
sensitivity of the result. None depends on this machine's rounding, so the tests pass on any
x86-64 CPU/BLAS (they also hold for pairwise or blocked summation, which only lower the error).
"""

from __future__ import annotations

import re

import numpy as np

EPS = np.finfo(np.float64).eps
_REPORT = bool(__import__("os").environ.get("GP_TOL_REPORT"))


def gamma(n: int) -> float:
    """Higham's ``gamma_n``: the relative error bound of an ``n``-term sum or product chain."""
    u = EPS / 2
    return n * u / (1 - n * u)


def kernel_rtol(kernel, *xis) -> float:
    """Relative rounding of a float64 ADP kernel entry: the scaled squared distance is a
    ``2b``-term sum whose absolute error ``gamma(2b + 2) max |xi / l|^2`` becomes a relative error
    of ``exp``; ``m + 1`` products and a sum over the components add ``gamma(m + 4)``."""
    b, c = kernel.input_dim, kernel.n_components
    big = max(float(np.max(np.sum((np.atleast_2d(x)[None] / kernel.lengthscales[:, None]) ** 2,
                                  axis=2))) for x in xis)
    return gamma(2 * b + 2) * 4 * big + gamma(c + 3)


def _abs_solve(a: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    return np.abs(np.linalg.solve(a, rhs))


def sparse_affine_tolerance(gp, xs, data=None, extra_jitter: float = 0.0, rows=None):
    """Absolute tolerances ``(tol_b (N, m+1), tol_sigma (N, m+1, m+1))`` between two float64
    evaluations of a sparse learner's affine predictive (eq. 20) at ``xs``.

    Both evaluations are backward stable for ``Sig = K_oo + S/s2``, ``K_oo`` and ``r`` (whether
    they factor, whiten or invert them, Higham ch. 8-14). A relative perturbation ``g`` of those
    changes ``b = Kt Sig^-1 r / s2`` by at most ``g |Kt Sig^-1| (|r| + |Sig| |w| s2) / s2`` and
    ``Sigma = diag(s) - Kt K_oo^-1 Kt' + Kt Sig^-1 Kt'`` by at most
    ``g (|Kt K_oo^-1| |K_oo| |K_oo^-1 Kt'| + |Kt Sig^-1| |Sig| |Sig^-1 Kt'|)``. With only the
    algebra differing, ``g = gamma(M)`` and the magnitudes are those of the matrices; with
    ``data = (xi, u, z, weights)``, one side (a streaming learner, or a reference formula)
    accumulated ``S`` and ``r`` from the data, so ``g = gamma(N + M)`` on the magnitudes
    ``|K_ox| Lambda |K_xo|`` and ``|K_ox| Lambda |z|`` (plus the kernel entries' rounding).
    The cancellation of the three terms of ``Sigma`` adds ``3 gamma(M) sqrt(s_i s_j)``.
    ``extra_jitter``: what a jittered Cholesky retry added to ``K_oo`` (it is the matrix used).
    ``rows`` (R, M): instead of ``Kt`` at ``xs``, tolerances of ``rows w`` (R,) and
    ``rows Sig^-1 rows'`` (R, R) (e.g. ``rows = K_oo`` for ``q(f_o)``'s mean and covariance).
    """
    kern = gp.kernel_
    xo, uo = gp.inducing_xi_, gp.inducing_u_
    m = len(xo)
    s2 = gp.noise_variance_
    koo = kern(xo, uo) + (gp.jitter_ + extra_jitter) * np.eye(m)
    if data is None:
        S, r = gp.S_, gp.r_
        mag_s, mag_r, g = np.abs(S), np.abs(r), gamma(m)
    else:
        xi, u, z, w = data
        kxo = kern(xi, u, xo, uo)
        S, r = kxo.T @ (w[:, None] * kxo), kxo.T @ (w * z)
        g = gamma(len(z) + m) + kernel_rtol(kern, xi, xo)
        mag_s = np.abs(kxo).T @ (w[:, None] * np.abs(kxo))
        mag_r = np.abs(kxo).T @ (w * np.abs(z))
    sig = koo + S / s2
    w_post = np.linalg.solve(sig, r) / s2
    pert = np.abs(koo) + mag_s / s2

    def tol(k):
        ks = _abs_solve(sig, k.T).T  # |k Sig^-1| (Sig symmetric)
        kk = _abs_solve(koo, k.T).T  # |k K_oo^-1|
        return (g * ks @ (mag_r / s2 + pert @ np.abs(w_post)),
                g * (ks @ pert @ ks.T + kk @ np.abs(koo) @ kk.T))

    if rows is not None:
        tb, ts = tol(np.asarray(rows))
        return tb, ts + 3 * gamma(m) * np.max(np.abs(koo))
    var = kern.variances
    scale = np.sqrt(np.outer(var, var))
    out = [tol(k) for k in kern.cross_affine(xs, xo, uo)]  # Kt: [N, c, M]
    return (np.array([t[0] for t in out]),
            np.array([t[1] for t in out]) + 3 * gamma(m) * scale)


def exact_affine_tolerance(gp, xs):
    """As :func:`sparse_affine_tolerance` for the exact GP: backward error ``gamma(N)`` of
    ``K + s2 I`` through ``b = Kt (K + s2 I)^-1 z`` and ``Sigma = diag(s) - Kt (K + s2 I)^-1 Kt'``
    (and the kernel entries' rounding)."""
    kern = gp.kernel_
    xi, u, z = gp.xi_train_, gp.u_train_, gp.z_train_
    n = len(z)
    kmat = kern(xi, u) + gp.noise_variance_ * np.eye(n)
    g = gamma(n) + kernel_rtol(kern, xi, xs)
    alpha = np.abs(np.linalg.solve(kmat, z))
    var = kern.variances
    tol_b, tol_s = [], []
    for k in kern.cross_affine(xs, xi, u):
        ks = _abs_solve(kmat, k.T).T
        tol_b.append(g * ks @ np.abs(kmat) @ alpha + g * np.abs(k) @ alpha)
        tol_s.append(g * (ks @ np.abs(kmat) @ ks.T + 2 * np.abs(k) @ ks.T)
                     + 3 * gamma(n) * np.sqrt(np.outer(var, var)))
    return np.array(tol_b), np.array(tol_s)


def contraction_tolerance(ubar_rows, tol_b, tol_sigma, bvec, sigma, gp_terms=None):
    """Tolerances of ``mean = b . ubar`` and ``var = ubar' Sigma ubar`` given the tolerances of
    ``b`` and ``Sigma`` (and the rounding of the contractions themselves)."""
    au = np.abs(ubar_rows)
    c = au.shape[1]
    tol_mean = np.einsum("ni,ni->n", au, tol_b + gamma(c + 1) * np.abs(bvec))
    tol_var = np.einsum("ni,nij,nj->n", au, tol_sigma + gamma(c * c + 1) * np.abs(sigma), au)
    return tol_mean, tol_var


def assert_within(got, ref, tol, what=""):
    """Elementwise ``|got - ref| <= tol`` with a readable failure."""
    err = np.abs(np.asarray(got) - np.asarray(ref))
    bad = err > tol
    if _REPORT:
        print(f"[tol] {what}: max err {err.max():.2e}, max tol {np.max(tol):.2e}, "
              f"max err/tol {np.max(err / np.maximum(tol, 1e-300)):.2e}")
    assert not np.any(bad), (f"{what}: {int(bad.sum())} entries beyond tolerance; worst "
                             f"|err| {err.max():.3g}, err/tol {np.max(err / tol):.3g}")


def central_difference(fun, x: np.ndarray, h: float):
    """Central differences of the scalar ``fun`` at ``x`` (step ``h`` in every coordinate) and
    an error bound for each: ``|D(h) - D(2h)|``, three times Richardson's estimate of the
    truncation error ``|D(h) - D(2h)| / 3`` (margin for the next order), plus the rounding
    ``4 EPS scale / h``, where ``scale`` is what ``fun`` returns as its second value (the
    magnitude of the terms it sums)."""
    fd, err = np.empty_like(x), np.empty_like(x)
    for j in range(len(x)):
        e = np.zeros_like(x)
        e[j] = h
        vals = {}
        for k in (1, -1, 2, -2):
            vals[k] = fun(x + k * e)
        d1 = (vals[1][0] - vals[-1][0]) / (2 * h)
        d2 = (vals[2][0] - vals[-2][0]) / (4 * h)
        scale = max(abs(v[1]) for v in vals.values())
        fd[j] = d1
        err[j] = abs(d1 - d2) + 4 * EPS * scale / h
    return fd, err


def warned_jitter(record) -> float:
    """The jitter a ``jittered_cholesky`` warning reports (``needed jitter X``)."""
    for w in record:
        match = re.search(r"needed jitter ([0-9.eE+-]+)", str(w.message))
        if match:
            return float(match.group(1))
    raise AssertionError("no jitter warning")


__all__ = ["EPS", "assert_within", "central_difference", "contraction_tolerance",
           "exact_affine_tolerance", "gamma", "kernel_rtol", "sparse_affine_tolerance",
           "warned_jitter"]
