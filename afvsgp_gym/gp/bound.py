"""Weighted collapsed Titsias bound (paper eq. 23, as corrected in DESIGN.md) and its gradient.

With weights ``lambda_t`` (``phi**age``; all ones gives Titsias 2009, eq. 18), inducing set ``o``,
``Q = K_xo K_oo^-1 K_ox`` and noise ``s2``, the bound on the weighted log likelihood is

    F = log N(z | 0, Q + s2 Lambda^-1) - (sum(lambda) - N)/2 log(2 pi s2)
        - 1/2 sum(log lambda) - 1/(2 s2) sum_t lambda_t (k_tt - Q_tt).

(The last-but-one term is a constant that makes F the exact weighted ELBO; the paper's eq. 23
has ``1/(2 s2)`` on the log term and the wrong sign on the trace.) It depends on the data only
through ``S = K_ox Lambda K_xo``, ``r = K_ox Lambda z``, ``sum(lambda z^2)``, ``sum(lambda)``
and ``sum(lambda k_tt)``; with ``Sig = K_oo + S / s2`` (``= B^-1``, DESIGN):

    noise_term  = -sum(lambda)/2 log(2 pi s2)
    logdet_term = -1/2 log|Sig| + 1/2 log|K_oo|
    fit_term    = -sum(lambda z^2) / (2 s2) + r' Sig^-1 r / (2 s2^2)
    trace_term  = -(sum(lambda k_tt) - tr(K_oo^-1 S)) / (2 s2)
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.linalg import cho_solve

from afvsgp_gym.gp._linalg import jittered_cholesky, ubar
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["BoundTerms", "SuffStats", "bound_terms", "suff_stats", "weighted_bound",
           "weighted_bound_and_grad"]


class SuffStats(NamedTuple):
    """Weighted data statistics over the inducing set (M = number of inducing points)."""

    koo: np.ndarray  # [M, M] K_oo + jitter I
    kxo: np.ndarray  # [N, M]
    S: np.ndarray  # [M, M] K_ox Lambda K_xo
    r: np.ndarray  # [M] K_ox Lambda z
    yy: float  # sum(lambda z^2)
    wsum: float  # sum(lambda)
    tr_k: float  # sum(lambda k_tt)


class BoundTerms(NamedTuple):
    """The four named terms of the weighted collapsed bound; ``total`` is their sum."""

    noise_term: float
    logdet_term: float
    fit_term: float
    trace_term: float

    @property
    def total(self) -> float:
        return self.noise_term + self.logdet_term + self.fit_term + self.trace_term


def suff_stats(kernel: ADPKernel, xi, u, z, weights, xi_o, u_o, jitter: float) -> SuffStats:
    """Statistics of (xi (N,b), u (N,m), z (N,), weights (N,)) on inducing (xi_o, u_o)."""
    ub, ub_o = ubar(u), ubar(u_o)
    koo = kernel._gram(xi_o, ub_o)
    koo[np.diag_indices_from(koo)] += jitter
    kxo = kernel._gram(xi, ub, xi_o, ub_o)
    wk = kxo * weights[:, None]
    return SuffStats(koo, kxo, kxo.T @ wk, wk.T @ z, float(weights @ (z * z)),
                     float(np.sum(weights)), float(weights @ kernel._diag(ub)))


def bound_terms(stats: SuffStats, noise_variance: float) -> BoundTerms:
    """Evaluate the named terms from sufficient statistics."""
    s2 = float(noise_variance)
    l_oo = jittered_cholesky(stats.koo, name="K_oo")
    l_sig = jittered_cholesky(stats.koo + stats.S / s2, name="K_oo + S/s2")
    a = cho_solve((l_sig, True), stats.r, check_finite=False)
    tr_q = float(np.trace(cho_solve((l_oo, True), stats.S, check_finite=False)))
    return BoundTerms(
        noise_term=-0.5 * stats.wsum * np.log(2.0 * np.pi * s2),
        logdet_term=float(np.sum(np.log(np.diag(l_oo))) - np.sum(np.log(np.diag(l_sig)))),
        fit_term=float(-stats.yy / (2.0 * s2) + stats.r @ a / (2.0 * s2 * s2)),
        trace_term=-(stats.tr_k - tr_q) / (2.0 * s2),
    )


def weighted_bound(kernel: ADPKernel, noise_variance: float, xi, u, z, weights, xi_o, u_o,
                   jitter: float = 0.0) -> BoundTerms:
    """Weighted collapsed bound (eq. 23 corrected) as named terms."""
    stats = suff_stats(kernel, xi, u, z, np.asarray(weights, dtype=float), xi_o, u_o, jitter)
    return bound_terms(stats, noise_variance)


def weighted_bound_and_grad(params: np.ndarray, kernel: ADPKernel, xi, u, z, weights, xi_o,
                            u_o, jitter: float = 0.0) -> tuple[float, np.ndarray]:
    """Bound and its gradient w.r.t. ``params = concat(kernel.theta, [log s2])``.

    ``kernel`` supplies the structure; its parameters are replaced by ``params[:-1]``
    (the object is modified). Gradients are analytic (chain rule through K_oo, K_xo, diag).
    """
    kernel.theta = params[:-1]
    s2 = float(np.exp(params[-1]))
    weights = np.asarray(weights, dtype=float)
    ub, ub_o = ubar(u), ubar(u_o)
    st = suff_stats(kernel, xi, u, z, weights, xi_o, u_o, jitter)
    l_oo = jittered_cholesky(st.koo, name="K_oo")
    l_sig = jittered_cholesky(st.koo + st.S / s2, name="K_oo + S/s2")
    m = st.koo.shape[0]
    eye = np.eye(m)
    koo_inv = cho_solve((l_oo, True), eye, check_finite=False)
    sig_inv = cho_solve((l_sig, True), eye, check_finite=False)
    a = sig_inv @ st.r  # [M]
    kis = koo_inv @ st.S  # [M, M]
    tr_q = float(np.trace(kis))
    ra = float(st.r @ a)
    value = (-0.5 * st.wsum * np.log(2.0 * np.pi * s2)
             + float(np.sum(np.log(np.diag(l_oo))) - np.sum(np.log(np.diag(l_sig))))
             - st.yy / (2.0 * s2) + ra / (2.0 * s2 * s2)
             - (st.tr_k - tr_q) / (2.0 * s2))
    aa = np.outer(a, a)
    # dF/dK_oo, dF/dS, dF/dr (matrices treated as unconstrained, all symmetric here)
    g_koo = (-0.5 * sig_inv + 0.5 * koo_inv - aa / (2.0 * s2 * s2)
             - kis @ koo_inv / (2.0 * s2))
    g_s = -sig_inv / (2.0 * s2) - aa / (2.0 * s2 ** 3) + koo_inv / (2.0 * s2)
    g_r = a / (s2 * s2)
    # chain to K_xo: S = K_ox Lambda K_xo, r = K_ox Lambda z
    g_kxo = 2.0 * (weights[:, None] * st.kxo) @ g_s + np.outer(weights * z, g_r)
    grad_theta = (kernel.grad_contract(0.5 * (g_koo + g_koo.T), xi_o, ub_o)
                  + kernel.grad_contract(g_kxo, xi, ub, xi_o, ub_o)
                  + kernel.grad_diag_contract(-weights / (2.0 * s2), ub))
    d_s2 = (-st.wsum / (2.0 * s2)
            + float(np.sum(sig_inv * st.S)) / (2.0 * s2 * s2)
            + st.yy / (2.0 * s2 * s2)
            - ra / s2 ** 3 + float(a @ st.S @ a) / (2.0 * s2 ** 4)
            + (st.tr_k - tr_q) / (2.0 * s2 * s2))
    return float(value), np.concatenate([grad_theta, [d_s2 * s2]])
