"""Common learner plumbing: validation, fitted checks, predict / predict_affine wrappers, and the
sparse (Titsias) predictive cache shared by VSGP and AFVSGP."""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

from afvsgp_gym.gp._linalg import check_batch, check_matrix, jittered_cholesky, ubar
from afvsgp_gym.gp._sparse import InducingCache, affine_from_kt
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["BaseLearner", "SparseLearner"]


def _check_positive(value, name: str) -> float:
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value}")
    return value


class BaseLearner:
    """Validation and the public predict methods; subclasses implement ``_predict`` and
    ``_predict_affine`` on validated float64 arrays."""

    kernel_: ADPKernel
    noise_variance_: float

    def _init_hyper(self, xi, u, z):
        """Kernel and noise from the constructor or the data (never modifies parameters)."""
        if self.kernel is not None:
            if not isinstance(self.kernel, ADPKernel):
                raise ValueError("kernel must be an ADPKernel or None")
            if self.kernel.input_dim != xi.shape[1] or self.kernel.action_dim != u.shape[1]:
                raise ValueError(
                    f"kernel is for b={self.kernel.input_dim}, m={self.kernel.action_dim} but "
                    f"xi has {xi.shape[1]} columns and u has {u.shape[1]}")
            kernel = self.kernel.clone()
        else:
            kernel = ADPKernel.from_data(xi, u, z)
        if self.noise_variance is not None:
            noise = _check_positive(self.noise_variance, "noise_variance")
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
    """Titsias posterior from (chol K_oo, S, r): ``Sig = K_oo + S/s2 = B^-1``,
    mean weights ``w = B r / s2``, ``D = K_oo^-1 - B`` (DESIGN, eq. 20).

    ``S`` and ``r`` live in one Fortran array ``_stats = scale * [r, S]`` (M, M+1), so a new
    sample ``(k, z)`` is a single BLAS rank-one update ``_stats += scale k [z, k']``; the scalar
    ``_scale`` absorbs AFVSGP's forgetting (``phi S`` becomes ``scale /= phi``).
    """

    def _fit_hyperparameters(self, xi, u, z, weights, learn_hyperparameters):
        """Initial kernel/noise, inducing set and jitter; maximise the weighted bound (eq. 23).

        Returns ``(kernel, noise, xo, uo, jitter, bound)``; ``bound`` is None without learning.
        Needs ``_initial_inducing``, ``jitter``, ``inducing`` and ``max_iter`` on the subclass.
        """
        from afvsgp_gym.gp._sparse import fit_bound

        kernel, noise = self._init_hyper(xi, u, z)
        xo, uo = self._initial_inducing(kernel, xi, u)
        jitter = self.jitter * float(np.mean(kernel.diag(xi, u)))
        bound = None
        if learn_hyperparameters:
            kernel, noise, bound = fit_bound(kernel, noise, xi, u, z, weights, xo, uo, jitter,
                                             self.max_iter)
            if self.inducing is None:
                xo, uo = self._initial_inducing(kernel, xi, u)
            jitter = self.jitter * float(np.mean(kernel.diag(xi, u)))
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
        m = low.shape[0]
        self._eye = np.eye(m)
        self._koo_inv = dpotrs(low, self._eye, lower=1)[0]
        self._dirty = True

    def _refresh_posterior(self) -> None:
        """Factor ``Sig = K_oo + S/s2`` and cache ``B = Sig^-1``, ``w = B r / s2`` and
        ``D = K_oo^-1 - B`` (then a prediction is three small matrix products)."""
        s2 = self.noise_variance_
        inv_s = 1.0 / (s2 * self._scale)
        stats = self._stats
        sig = self._koo + stats[:, 1:] * inv_s
        if not sig.flags.f_contiguous:
            sig = sig.T  # symmetric: the Fortran view avoids a copy in LAPACK
        low, info = dpotrf(sig, lower=1, clean=1, overwrite_a=1)
        if info != 0:
            low = jittered_cholesky(self._koo + stats[:, 1:] * inv_s, name="K_oo + S/s2")
        inv = dpotrs(low, self._eye, lower=1)[0]  # B (full, symmetric)
        self._b_mat = inv
        w = inv @ stats[:, 0]
        w *= inv_s
        self._w = w
        self._d_mat = self._koo_inv - inv
        self._dirty = False

    def _dense(self) -> None:
        if self._dirty:
            self._refresh_posterior()

    def _predict_affine(self, xi):
        if self._dirty:
            self._refresh_posterior()
        if xi.shape[0] == 1:  # the per-control-step path
            kt = self._ind.kt(xi[0])  # [m+1, M], eq. 21
            bvec = kt @ self._w  # eq. 20 mean, per component
            sig = kt @ (self._d_mat @ kt.T)  # Kt (K_oo^-1 - B) Kt'
            sig += sig.T
            sig *= -0.5
            sig += self._ind.var_diag
            return bvec[None, :], sig[None, :, :]
        return affine_from_kt(self._ind.kt_batch(xi), self._ind.var, self._w, self._d_mat)

    def _predict(self, xi, u):
        self._dense()
        kt = self._ind.kt_batch(xi)
        k_so = np.einsum("ni,nij->nj", ubar(u), kt)  # [N, M]
        mean = k_so @ self._w
        var = self.kernel_._diag(ubar(u)) - np.einsum("nj,jk,nk->n", k_so, self._d_mat, k_so)
        return mean, var

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
        """(M, M) ``(K_oo + S/s2)^-1`` (copy)."""
        self._dense()
        return self._b_mat.copy()
