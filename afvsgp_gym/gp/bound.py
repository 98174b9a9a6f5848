"""Weighted collapsed Titsias bound (paper eq. 23, as corrected below) and its gradient, in the
whitened form every sparse learner shares.

With weights ``lambda_t`` (``phi**age``; all ones gives Titsias 2009, eq. 18), inducing set ``o``,
``Q = K_xo K_oo^-1 K_ox`` and noise ``s2``, the bound on the weighted log likelihood is

    F = log N(z | 0, Q + s2 Lambda^-1) - (sum(lambda) - N)/2 log(2 pi s2)
        - 1/2 sum(log lambda) - 1/(2 s2) sum_t lambda_t (k_tt - Q_tt).

(The last-but-one term is a constant that makes F the exact weighted ELBO; the paper's eq. 23
has ``1/(2 s2)`` on the log term and the wrong sign on the trace.)

Whitened form (Titsias 2009; GPflow's SGPR). With ``L = chol(K_oo)`` (jitter included),

    A = L^-1 K_ox Lambda^1/2 / s   (M, N),     y = Lambda^1/2 z / s,
    D = I + A A' = I + L^-1 S L^-T / s2,       L_D = chol(D),
    v = A y = L^-1 r / s2,                     c = L_D^-1 v,

where ``S = K_ox Lambda K_xo`` and ``r = K_ox Lambda z``. Since ``K_oo + S/s2 = L D L'``, the
determinant lemma and Woodbury's identity give ``log|Q + s2 Lambda^-1| = log|s2 Lambda^-1| +
log|D|`` and ``z' (Q + s2 Lambda^-1)^-1 z = y'y - c'c``, ``tr(K_oo^-1 S) / s2 = |A|_F^2``, so

    F = -sum(lambda)/2 log(2 pi s2) - sum(log diag L_D) - (y'y - c'c)/2
        - sum(lambda k_tt)/(2 s2) + |A|_F^2/2,

and, with ``alpha = D^-1 v = L_D^-T c`` and the whitened residual ``e = y - A' alpha =
(I + A'A)^-1 y``, ``y'y - c'c = |e|^2 + |alpha|^2`` (a sum of squares, used for the fit term).

Why this form: ``D >= I``, so its factorisation is stable however ill-conditioned ``K_oo`` or
``K_oo + S/s2`` is (the learned hyperparameters make the latter reach 1e12 on the Franka
warm-up data), and nothing is inverted explicitly: ``L`` and ``L_D`` enter through triangular
solves only. The unwhitened form ``log|K_oo + S/s2| - log|K_oo|`` subtracts two logs of
determinants whose small eigenvalues carry rounding of relative size ``eps cond``.

Gradient (reverse mode through the two factorisations)::

    Abar = dF/dA = (I - D^-1 - alpha alpha') A + alpha y' = A - D^-1 A + alpha e'
    dF/dK_ox = L^-T Abar Lambda^1/2 / s
    dF/dK_oo = -1/2 L^-T sym(Abar A') L^-1        (Cholesky adjoint; Abar A' is symmetric in
                                                   exact arithmetic since F is invariant to
                                                   L -> L Q, Q orthogonal)
    dF/dk_tt = -lambda_t / (2 s2)
    dF/dlog s2 = -sum(lambda)/2 + sum lambda (k_tt - Q_tt) / (2 s2) + tr(D^-1 A A')/2 + |e|^2/2

(``A`` and ``y`` scale as ``1/s``; the last line regroups ``y'y - tr(Abar A') - alpha'v`` into
non-negative terms.) The relative jitter of the fit (:func:`jitter_for`) adds
``tr(dF/dK_oo) d eps / d theta``.

The relation to GPyTorch's ``SGPR`` and GPflow's ``SGPR`` is in docs/learners.md ("Conventions
against GPyTorch and GPflow").
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.linalg.blas import dsyrk, dtrsm
from scipy.linalg.lapack import dtrtrs

from afvsgp_gym.gp._linalg import jitter_for, jittered_cholesky, ubar
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["BoundTerms", "WhitenedPosterior", "weighted_bound", "weighted_bound_and_grad"]


def _tri(low: np.ndarray, rhs: np.ndarray, trans: int = 0) -> np.ndarray:
    """``L^-1 rhs`` (``trans=0``) or ``L^-T rhs`` (``trans=1``) for a lower factor ``L``."""
    x, info = dtrtrs(low, rhs, lower=1, trans=trans)
    if info != 0:
        raise np.linalg.LinAlgError("singular triangular factor")
    return x


class BoundTerms(NamedTuple):
    """The four named terms of the weighted collapsed bound; ``total`` is their sum.

    ``noise_term = -sum(lambda)/2 log(2 pi s2)``, ``logdet_term = -1/2 log|D|``,
    ``fit_term = -(y'y - c'c)/2`` and ``trace_term = -sum lambda (k_tt - Q_tt) / (2 s2)``.
    """

    noise_term: float
    logdet_term: float
    fit_term: float
    trace_term: float

    @property
    def total(self) -> float:
        return self.noise_term + self.logdet_term + self.fit_term + self.trace_term


class WhitenedPosterior:
    """The sparse posterior (paper eq. 20) from ``L = chol(K_oo)`` and the whitened statistics
    ``P = A A' = L^-1 S L^-T / s2`` and ``v = L^-1 r / s2``.

    ``q(f_o)`` has covariance ``K_oo (K_oo + S/s2)^-1 K_oo = L D^-1 L'`` and mean
    ``K_oo (K_oo + S/s2)^-1 r / s2 = L D^-1 v``. A prediction at a point with cross-covariance
    ``k`` (M,) has mean ``k' w``, ``w = L^-T L_D^-T c``, and variance
    ``k_** - |L^-1 k|^2 + |L_D^-1 L^-1 k|^2`` (Nystroem residual plus the posterior's share).

    Accuracy: ``P`` from the data (:meth:`from_data`, ``A = L^-1 K_ox Lambda^1/2 / s``) carries
    no factor of ``cond(K_oo)``; ``P`` from accumulated statistics (:meth:`from_stats`, what a
    streaming learner has) inherits the rounding of ``S``, amplified by ``|L^-1|^2``.
    """

    __slots__ = ("l_oo", "l_d", "c", "w")

    def __init__(self, l_oo: np.ndarray, p: np.ndarray, v: np.ndarray,
                 l_d: np.ndarray | None = None):
        if l_d is None:  # l_d: chol(I + P) if the caller has it already
            d = 0.5 * (p + p.T)
            d[np.diag_indices(d.shape[0])] += 1.0
            l_d = jittered_cholesky(d, name="I + L^-1 S L^-T / s2")
        self.l_oo = l_oo
        self.l_d = l_d
        self.c = _tri(self.l_d, v)
        self.w = _tri(l_oo, _tri(self.l_d, self.c, 1), 1)

    @classmethod
    def from_stats(cls, l_oo: np.ndarray, S: np.ndarray, r: np.ndarray,
                   noise_variance: float) -> WhitenedPosterior:
        """From ``S = K_ox Lambda K_xo`` and ``r = K_ox Lambda z`` (two triangular solves)."""
        s2 = float(noise_variance)
        return cls(l_oo, _tri(l_oo, _tri(l_oo, S).T).T / s2, _tri(l_oo, r) / s2)

    @classmethod
    def from_data(cls, l_oo: np.ndarray, kxo: np.ndarray, z: np.ndarray, weights,
                  noise_variance: float) -> WhitenedPosterior:
        """From ``K_xo`` (N, M), targets and weights: ``A = L^-1 K_ox Lambda^1/2 / s`` (one BLAS
        triangular solve and one ``syrk``, O(N M^2))."""
        s = np.sqrt(float(noise_variance))
        sq_w = np.sqrt(np.broadcast_to(np.asarray(weights, dtype=float), z.shape))
        rhs = kxo.T if np.all(sq_w == 1.0) else (kxo * sq_w[:, None]).T
        a = dtrsm(1.0 / s, l_oo, rhs, lower=1)  # [M, N]
        p = dsyrk(1.0, a)  # upper triangle of A A'
        p = np.triu(p) + np.triu(p, 1).T
        return cls(l_oo, p, a @ (sq_w * z / s))

    def whiten(self, kt: np.ndarray):
        """``(G, H)`` for cross-covariances ``kt`` (..., M): ``G = L^-1 kt'``,
        ``H = L_D^-1 G`` (each (M, ...)), so ``kt K_oo^-1 kt' = G'G`` and
        ``kt (K_oo + S/s2)^-1 kt' = H'H``."""
        flat = kt.reshape(-1, kt.shape[-1]).T
        g = _tri(self.l_oo, flat)
        return g, _tri(self.l_d, g)

    def affine(self, kt: np.ndarray, var: np.ndarray):
        """Affine predictive (eq. 20) from ``Kt`` (N, m+1, M) and the component variances
        ``var`` (m+1,): ``b = Kt w`` (N, m+1), ``Sigma = diag(var) - G'G + H'H`` (N, m+1, m+1),
        exactly symmetric."""
        n, c, m = kt.shape
        g, h = self.whiten(kt)
        g = g.T.reshape(n, c, m)
        h = h.T.reshape(n, c, m)
        sig = np.matmul(h, h.transpose(0, 2, 1))
        sig -= np.matmul(g, g.transpose(0, 2, 1))
        sig = 0.5 * (sig + sig.transpose(0, 2, 1))
        idx = np.arange(c)
        sig[:, idx, idx] += var
        return kt @ self.w, sig

    def predict(self, k_so: np.ndarray, k_ss: np.ndarray):
        """Mean and variance (N,) from ``k_so`` (N, M) and the prior variances ``k_ss`` (N,)."""
        g, h = self.whiten(k_so)
        return k_so @ self.w, k_ss - np.einsum("mn,mn->n", g, g) + np.einsum("mn,mn->n", h, h)

    def precision_inverse(self) -> np.ndarray:
        """``(K_oo + S/s2)^-1 = L^-T D^-1 L^-1`` as a dense matrix (diagnostics only)."""
        linv_t = _tri(self.l_oo, np.eye(self.l_oo.shape[0])).T  # L^-T
        x = _tri(self.l_d, linv_t.T)  # L_D^-1 L^-1
        return x.T @ x


class _Pieces(NamedTuple):
    comp_oo: np.ndarray  # kernel components of K_oo and K_xo (reused by the gradient)
    comp_xo: np.ndarray
    l_oo: np.ndarray
    a: np.ndarray  # [M, N]
    l_d: np.ndarray
    alpha: np.ndarray  # D^-1 A y
    e: np.ndarray  # y - A' alpha = (I + A'A)^-1 y
    terms: BoundTerms


def _evaluate(kernel: ADPKernel, s2: float, xi, ub, z, weights, xi_o, ub_o, jitter: float,
              relative: bool) -> _Pieces:
    comp_oo = kernel._components(xi_o, None)
    comp_xo = kernel._components(xi, xi_o)
    koo = kernel._gram(xi_o, ub_o, comp=comp_oo)
    eps = jitter_for(koo, jitter) if relative else float(jitter)
    koo[np.diag_indices_from(koo)] += eps
    kxo = kernel._gram(xi, ub, xi_o, ub_o, comp=comp_xo)
    l_oo = jittered_cholesky(koo, name="K_oo")
    sq_w = np.sqrt(weights)
    s = np.sqrt(s2)
    a = _tri(l_oo, (kxo * (sq_w / s)[:, None]).T)  # [M, N]
    y = sq_w * z / s
    m = a.shape[0]
    d = a @ a.T
    d[np.diag_indices(m)] += 1.0
    l_d = jittered_cholesky(d, name="I + A A'")
    v = a @ y
    alpha = _tri(l_d, _tri(l_d, v), 1)
    e = y - alpha @ a
    kdiag = kernel._diag(ub)
    terms = BoundTerms(
        noise_term=-0.5 * float(np.sum(weights)) * np.log(2.0 * np.pi * s2),
        logdet_term=-float(np.sum(np.log(np.diag(l_d)))),
        fit_term=-0.5 * float(e @ e + alpha @ alpha),
        trace_term=-0.5 * float(weights @ kdiag / s2 - np.sum(a * a)),
    )
    return _Pieces(comp_oo, comp_xo, l_oo, a, l_d, alpha, e, terms)


def weighted_bound(kernel: ADPKernel, noise_variance: float, xi, u, z, weights, xi_o, u_o,
                   jitter: float = 0.0) -> BoundTerms:
    """Weighted collapsed bound (eq. 23 corrected) as named terms; ``jitter`` is added to the
    diagonal of ``K_oo`` (absolute)."""
    return _evaluate(kernel, float(noise_variance), xi, ubar(u), z,
                     np.asarray(weights, dtype=float), xi_o, ubar(u_o), jitter, False).terms


def weighted_bound_and_grad(params: np.ndarray, kernel: ADPKernel, xi, u, z, weights, xi_o,
                            u_o, jitter: float = 0.0, *,
                            relative_jitter: bool = False) -> tuple[float, np.ndarray]:
    """Bound and its gradient w.r.t. ``params = concat(kernel.theta, [log s2])``.

    ``kernel`` supplies the structure; its parameters are replaced by ``params[:-1]`` (the
    object is modified). ``jitter`` is absolute, or with ``relative_jitter`` the factor of
    :func:`afvsgp_gym.gp._linalg.jitter_for` (then the jitter follows the kernel and its
    derivative is included). Gradients are analytic (module docstring).
    """
    kernel.theta = params[:-1]
    s2 = float(np.exp(params[-1]))
    weights = np.asarray(weights, dtype=float)
    ub, ub_o = ubar(u), ubar(u_o)
    pc = _evaluate(kernel, s2, xi, ub, z, weights, xi_o, ub_o, jitter, relative_jitter)
    a, alpha, e = pc.a, pc.alpha, pc.e
    m = a.shape[0]
    d_inv_a = _tri(pc.l_d, _tri(pc.l_d, a), 1)  # D^-1 A
    abar = a - d_inv_a + np.outer(alpha, e)  # (I - D^-1 - alpha alpha') A + alpha y'
    abar_at = abar @ a.T
    abar_at = 0.5 * (abar_at + abar_at.T)
    g_koo = -0.5 * _tri(pc.l_oo, _tri(pc.l_oo, abar_at, 1).T, 1)  # -1/2 L^-T sym(.) L^-1
    s = np.sqrt(s2)
    g_kxo = (_tri(pc.l_oo, abar, 1) * (np.sqrt(weights) / s)).T  # [N, M]
    g_koo = 0.5 * (g_koo + g_koo.T)
    grad_theta = (kernel.grad_contract(g_koo, xi_o, ub_o, comp=pc.comp_oo)
                  + kernel.grad_contract(g_kxo, xi, ub, xi_o, ub_o, comp=pc.comp_xo)
                  + kernel.grad_diag_contract(-weights / (2.0 * s2), ub))
    if relative_jitter:  # eps = jitter * mean diag K_oo
        grad_theta += kernel.grad_diag_contract(
            np.full(m, float(jitter) * float(np.trace(g_koo)) / m), ub_o)
    d_log_s2 = (-0.5 * float(np.sum(weights)) - pc.terms.trace_term
                + 0.5 * float(np.sum(d_inv_a * a)) + 0.5 * float(e @ e))
    return float(pc.terms.total), np.concatenate([grad_theta, [d_log_s2]])
