"""Common learner plumbing: validation, fitted checks, predict / predict_affine wrappers, and the
sparse (Titsias) posterior shared by VSGP and AFVSGP."""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dpotrs

from afvsgp_gym.gp._linalg import (
    check_batch,
    check_matrix,
    check_real,
    jitter_for,
    jittered_cholesky,
    ubar,
)
from afvsgp_gym.gp._sparse import InducingCache, fit_collapsed
from afvsgp_gym.gp.bound import WhitenedPosterior, weighted_bound
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["BaseLearner", "SparseLearner"]


class BaseLearner:
    """Validation and the public predict methods; subclasses implement ``_predict`` and
    ``_predict_affine`` on validated float64 arrays."""

    kernel_: ADPKernel
    noise_variance_: float

    def _check_params(self) -> None:
        """Check the constructor parameters that need no data (``ValueError`` naming the
        first bad one); ``fit`` calls it, and the safety filter calls it when it is built, so
        that a bad ``learner_kwargs`` is refused then and not at the end of its warm-up."""
        if self.kernel is not None and not isinstance(self.kernel, ADPKernel):
            raise ValueError(f"kernel must be an ADPKernel or None, got {type(self.kernel)}")
        if self.noise_variance is not None:
            check_real(self.noise_variance, "noise_variance", low=0.0, low_open=True)

    def _init_hyper(self, xi, u, z):
        """Kernel and noise from the constructor or the data (never modifies parameters):
        ``ADPKernel.from_data`` and ``max(0.1 var(z), 1e-6)`` by default."""
        if self.kernel is not None:
            if not isinstance(self.kernel, ADPKernel):
                raise ValueError(f"kernel must be an ADPKernel or None, got {type(self.kernel)}")
            if self.kernel.input_dim != xi.shape[1] or self.kernel.action_dim != u.shape[1]:
                raise ValueError(
                    f"kernel is for b={self.kernel.input_dim}, m={self.kernel.action_dim} but "
                    f"xi has {xi.shape[1]} columns and u has {u.shape[1]}")
            kernel = self.kernel.clone()
        else:
            kernel = ADPKernel.from_data(xi, u, z)
        if self.noise_variance is not None:
            noise = check_real(self.noise_variance, "noise_variance", low=0.0, low_open=True)
        else:
            vz = float(np.var(z)) if z.shape[0] > 1 else float(np.mean(z * z))
            noise = max(0.1 * vz, 1e-6)
        return kernel, noise

    def _check_fitted(self) -> None:
        if not hasattr(self, "kernel_"):
            raise RuntimeError(f"{type(self).__name__} is not fitted; call fit first")

    def _validate_fit(self, xi, u, z):
        return check_batch(xi, u, z)

    def _dims(self):
        return self.kernel_.input_dim, self.kernel_.action_dim

    def predict(self, xi, u):
        """Latent mean (N,) and variance (N,) at (xi (N,b), u (N,m)) (paper eq. 20)."""
        self._check_fitted()
        b, m = self._dims()
        xi, u, _ = check_batch(xi, u, input_dim=b, action_dim=m)
        mean, var = self._predict(xi, u)
        return mean, np.maximum(var, 0.0)

    def predict_affine(self, xi):
        """``b`` (N, m+1), ``Sigma`` (N, m+1, m+1): mean ``b . ubar``, var ``ubar' Sigma ubar``."""
        try:
            b = self.kernel_._b
        except AttributeError:
            raise RuntimeError(f"{type(self).__name__} is not fitted; call fit first") from None
        if not (type(xi) is np.ndarray and xi.dtype == np.float64 and xi.ndim == 2
                and xi.shape[1] == b and xi.shape[0] > 0
                and math.isfinite(xi.sum())):  # fast path for well-formed arrays
            xi = check_matrix(xi, "xi", ncols=b)
            if xi.shape[0] == 0:
                raise ValueError("xi must contain at least one row")
        return self._predict_affine(xi)

    def _predict(self, xi, u):  # generic: through the affine form
        bvec, sig = self._predict_affine(xi)
        ub = ubar(u)
        return np.einsum("ni,ni->n", bvec, ub), np.einsum("ni,nij,nj->n", ub, sig, ub)


class SparseLearner(BaseLearner):
    """Weighted Titsias posterior (eq. 20) from ``chol(K_oo)`` and the statistics ``S``, ``r``,
    through :class:`~afvsgp_gym.gp.bound.WhitenedPosterior` (triangular solves only).

    ``S`` and ``r`` live in one Fortran array ``_stats = scale * [r, S]`` (M, M+1), so a new
    sample ``(k, z)`` is a single BLAS rank-one update ``_stats += scale k [z, k']``; the scalar
    ``_scale`` absorbs AFVSGP's forgetting (``phi S`` becomes ``scale /= phi``).

    Subclasses provide ``_initial_inducing(kernel, xi, u)`` and the constructor parameters
    ``jitter`` (relative, :func:`~afvsgp_gym.gp._linalg.jitter_for`), ``max_iter`` and ``prior``.
    """

    def _fit_hyperparameters(self, xi, u, z, weights, learn_hyperparameters):
        """Initial kernel/noise, inducing set and jitter; with ``learn_hyperparameters`` the
        weighted bound (eq. 23) plus the prior is maximised (:func:`fit_collapsed`).

        Returns ``(kernel, noise, xo, uo, jitter, bound)``: ``bound`` is the weighted collapsed
        bound of ``(xi, u, z, weights)`` at the returned hyperparameters, inducing set and
        (absolute) jitter.
        """
        kernel, noise = self._init_hyper(xi, u, z)
        if learn_hyperparameters:
            kernel, noise, (xo, uo) = fit_collapsed(
                kernel, noise, xi, u, z, weights,
                lambda k: self._initial_inducing(k, xi, u), jitter=self.jitter,
                maxiter=self.max_iter, prior=self.prior)
        else:
            xo, uo = self._initial_inducing(kernel, xi, u)
        jitter = jitter_for(kernel._gram(xo, ubar(uo)), self.jitter)
        bound = weighted_bound(kernel, noise, xi, u, z, weights, xo, uo, jitter).total
        return kernel, noise, xo, uo, jitter, bound

    def _set_stats(self, S: np.ndarray, r: np.ndarray) -> None:
        m = r.shape[0]
        st = np.empty((m, m + 1), order="F")
        st[:, 0] = r
        st[:, 1:] = S
        self._stats = st
        self._scale = 1.0
        self._dirty = True

    def _setup_inducing(self, xi_o, ub_o, capacity: int) -> None:
        self._ind = InducingCache(self.kernel_, capacity)
        self._ind.set(xi_o, ub_o)
        koo = self.kernel_._gram(xi_o, ub_o)
        koo[np.diag_indices_from(koo)] += self.jitter_
        self._koo = koo
        self._set_koo_chol(jittered_cholesky(koo, name="K_oo"))

    def _set_koo_chol(self, low: np.ndarray) -> None:
        self._l_oo = low
        # K_oo^-1 for AFVSGP's cheap eq. 27 screening only (confirmed through the factor before
        # a point is added); predictions and the bound never use it
        self._koo_inv = dpotrs(low, np.eye(low.shape[0]), lower=1)[0]
        self._dirty = True

    def _refresh_posterior(self) -> None:
        """Whitened posterior from ``L_oo`` and the current ``[r, S]`` (eq. 20)."""
        inv = 1.0 / self._scale
        st = self._stats
        self._post = WhitenedPosterior.from_stats(self._l_oo, st[:, 1:] * inv, st[:, 0] * inv,
                                                  self.noise_variance_)
        self._dirty = False

    def _posterior(self) -> WhitenedPosterior:
        if self._dirty:
            self._refresh_posterior()
        return self._post

    def _predict_affine(self, xi):
        post = self._posterior()
        if xi.shape[0] == 1:  # the per-control-step path
            kt = self._ind.kt(xi[0])[None]  # [1, m+1, M], eq. 21
        else:
            kt = self._ind.kt_batch(xi)
        return post.affine(kt, self._ind.var)

    def _predict(self, xi, u):
        post = self._posterior()
        ub = ubar(u)
        k_so = np.einsum("ni,nij->nj", ub, self._ind.kt_batch(xi))  # [N, M]
        return post.predict(k_so, self.kernel_._diag(ub))

    @property
    def inducing_xi_(self) -> np.ndarray:
        """(M, b) inducing features (copy)."""
        return self._ind.xi[: self._ind.M].copy()

    @property
    def inducing_u_(self) -> np.ndarray:
        """(M, m) inducing actions (copy)."""
        return self._ind.ub[: self._ind.M, 1:].copy()

    @property
    def S_(self) -> np.ndarray:
        """(M, M) ``K_ox Lambda K_xo`` (copy)."""
        return self._stats[:, 1:] / self._scale

    @property
    def r_(self) -> np.ndarray:
        """(M,) ``K_ox Lambda z`` (copy)."""
        return self._stats[:, 0] / self._scale

    @property
    def B_(self) -> np.ndarray:
        """(M, M) ``(K_oo + S/s2)^-1`` (a dense copy for diagnostics; predictions use the
        factors)."""
        return self._posterior().precision_inverse()
