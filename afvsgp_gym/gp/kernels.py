"""Affine Dot Product (ADP) compound kernel (paper eq. 19, Castaneda et al. 2021).

``k((xi, u), (xi', u')) = ubar' diag(k_1(xi, xi'), ..., k_{m+1}(xi, xi')) ubar'``,
``ubar = [1, u]``, with ARD squared-exponential components
``k_i(xi, xi') = s_i exp(-1/2 sum_d (xi_d - xi'_d)^2 / l_{i,d}^2)``.

The parameter vector ``theta`` is ``concat(log l.ravel(), log s)`` (length (m+1)(b+1)).
"""

from __future__ import annotations

import numpy as np

from afvsgp_gym.gp._linalg import check_batch, check_matrix, ubar

__all__ = ["ADPKernel"]


class ADPKernel:
    """ADP compound kernel with ``m+1`` ARD RBF components on ``b`` features.

    Parameters
    ----------
    lengthscales : array of shape (m+1, b)
        Positive ARD lengthscales, one row per component (row 0 multiplies the 1 in ubar).
    variances : array of shape (m+1,)
        Positive signal variances of the components.

    Attributes
    ----------
    theta : ndarray of shape ((m+1)*(b+1),)
        ``concat(log lengthscales.ravel(), log variances)``; settable.
    """

    def __init__(self, lengthscales, variances):
        ls = check_matrix(lengthscales, "lengthscales")
        var = check_matrix(variances, "variances", ndim=1, nrows=ls.shape[0])
        if np.any(ls <= 0):
            raise ValueError("lengthscales must be positive")
        if np.any(var <= 0):
            raise ValueError("variances must be positive")
        self._n_comp, self._b = ls.shape
        self._theta = np.concatenate([np.log(ls).ravel(), np.log(var)])
        self._cache()

    # ----------------------------------------------------------------- parameters
    def _cache(self) -> None:
        nl = self._n_comp * self._b
        self._ls = np.exp(self._theta[:nl]).reshape(self._n_comp, self._b)
        self._inv_ls = 1.0 / self._ls  # (m+1, b)
        self._var = np.exp(self._theta[nl:])

    @property
    def theta(self) -> np.ndarray:
        """Log parameters, a copy: ``concat(log lengthscales.ravel(), log variances)``."""
        return self._theta.copy()

    @theta.setter
    def theta(self, value) -> None:
        value = check_matrix(value, "theta", ndim=1, nrows=self.n_params)
        self._theta = value
        self._cache()

    @property
    def n_params(self) -> int:
        """Length of ``theta``."""
        return self._n_comp * (self._b + 1)

    @property
    def lengthscales(self) -> np.ndarray:
        """(m+1, b) lengthscales (copy)."""
        return self._ls.copy()

    @property
    def variances(self) -> np.ndarray:
        """(m+1,) component variances (copy)."""
        return self._var.copy()

    @property
    def input_dim(self) -> int:
        """Feature dimension b."""
        return self._b

    @property
    def action_dim(self) -> int:
        """Action dimension m."""
        return self._n_comp - 1

    @property
    def n_components(self) -> int:
        """m + 1."""
        return self._n_comp

    def clone(self) -> ADPKernel:
        """Independent copy with the same parameters."""
        return ADPKernel(self._ls, self._var)

    def with_theta(self, theta) -> ADPKernel:
        """Copy with parameters ``theta``."""
        k = self.clone()
        k.theta = theta
        return k

    def __repr__(self) -> str:
        return (f"ADPKernel(m+1={self._n_comp}, b={self._b}, "
                f"variances={np.array2string(self._var, precision=3)})")

    # ----------------------------------------------------------------- evaluation
    def _sqdist(self, xi1: np.ndarray, xi2: np.ndarray | None) -> np.ndarray:
        """Scaled squared distances (m+1, N1, N2)."""
        a = xi1[None, :, :] * self._inv_ls[:, None, :]  # (m+1, N1, b)
        na = np.einsum("inb,inb->in", a, a)
        if xi2 is None:
            d = na[:, :, None] + na[:, None, :] - 2.0 * np.matmul(a, a.transpose(0, 2, 1))
            idx = np.arange(xi1.shape[0])
            d[:, idx, idx] = 0.0
        else:
            c = xi2[None, :, :] * self._inv_ls[:, None, :]
            nc = np.einsum("inb,inb->in", c, c)
            d = na[:, :, None] + nc[:, None, :] - 2.0 * np.matmul(a, c.transpose(0, 2, 1))
        np.maximum(d, 0.0, out=d)
        return d

    def components(self, xi1, xi2=None) -> np.ndarray:
        """Individual RBF components ``k_i(xi1_n, xi2_j)``: (m+1, N1, N2)."""
        xi1 = check_matrix(xi1, "xi1", ncols=self._b)
        if xi2 is not None:
            xi2 = check_matrix(xi2, "xi2", ncols=self._b)
        return self._components(xi1, xi2)

    def _components(self, xi1: np.ndarray, xi2: np.ndarray | None) -> np.ndarray:
        d = self._sqdist(xi1, xi2)
        d *= -0.5
        np.exp(d, out=d)
        d *= self._var[:, None, None]
        return d

    def __call__(self, xi1, u1, xi2=None, u2=None) -> np.ndarray:
        """Gram matrix ``K[n, j] = k((xi1_n, u1_n), (xi2_j, u2_j))`` (N1, N2); eq. 19."""
        xi1, u1, _ = check_batch(xi1, u1, input_dim=self._b, action_dim=self._n_comp - 1)
        if (xi2 is None) != (u2 is None):
            raise ValueError("xi2 and u2 must be given together")
        if xi2 is not None:
            xi2 = check_matrix(xi2, "xi2", ncols=self._b)
            u2 = check_matrix(u2, "u2", ncols=self._n_comp - 1, nrows=xi2.shape[0])
        return self._gram(xi1, ubar(u1), xi2, None if u2 is None else ubar(u2))

    def _gram(self, xi1, ub1, xi2=None, ub2=None, comp=None) -> np.ndarray:
        """Gram from validated inputs with precomputed ubar (internal fast path); ``comp``:
        the components ``_components(xi1, xi2)`` if already computed."""
        if comp is None:
            comp = self._components(xi1, xi2)
        if ub2 is None:
            gram = np.einsum("ni,inj,ji->nj", ub1, comp, ub1)
            return 0.5 * (gram + gram.T)
        return np.einsum("ni,inj,ji->nj", ub1, comp, ub2)

    def diag(self, xi, u) -> np.ndarray:
        """``k(x_n, x_n)`` = sum_i s_i ubar_{n,i}^2: (N,)."""
        xi, u, _ = check_batch(xi, u, input_dim=self._b, action_dim=self._n_comp - 1)
        return self._diag(ubar(u))

    def _diag(self, ub: np.ndarray) -> np.ndarray:
        return (ub * ub) @ self._var

    def cross_affine(self, xi_star, xi2, u2) -> np.ndarray:
        """Per-component cross covariance (N*, m+1, N2).

        ``out[n, i, j] = k_i(xi*_n, xi2_j) ubar2_j[i]``, so
        ``k((xi*, u*), (xi2, u2)) = ubar* . out[n]`` (paper eq. 21).
        """
        xi_star = check_matrix(xi_star, "xi_star", ncols=self._b)
        xi2 = check_matrix(xi2, "xi2", ncols=self._b)
        u2 = check_matrix(u2, "u2", ncols=self._n_comp - 1, nrows=xi2.shape[0])
        return self._cross_affine(xi_star, xi2, ubar(u2))

    def _cross_affine(self, xi_star, xi2, ub2) -> np.ndarray:
        comp = self._components(xi_star, xi2)  # (m+1, N*, N2)
        return comp.transpose(1, 0, 2) * ub2.T[None, :, :]

    # ----------------------------------------------------------------- gradients
    def grad_contract(self, g: np.ndarray, xi1, ub1, xi2=None, ub2=None,
                      comp=None) -> np.ndarray:
        """``sum_{n,j} g[n, j] dK[n, j] / dtheta``: (n_params,).

        ``xi*`` are validated (N, b) arrays, ``ub*`` are ubar arrays (N, m+1) (see ``ubar``).
        With ``xi2 is None`` the gram is ``K(x1, x1)``. ``comp``: the components
        ``_components(xi1, xi2)`` if already computed.
        """
        same = xi2 is None
        if comp is None:
            comp = self._components(xi1, xi2)  # (m+1, N1, N2)
        if same:
            xi2, ub2 = xi1, ub1
        # W_i = g o (ub1_i ub2_i') o k_i
        w = comp * g[None, :, :]
        w *= ub1.T[:, :, None]
        w *= ub2.T[:, None, :]
        grad_var = w.sum(axis=(1, 2))  # d/dlog s_i
        # d k_i / d log l_{i,d} = k_i (x_d - x'_d)^2 / l_{i,d}^2
        rows = w.sum(axis=2)  # (m+1, N1)
        cols = w.sum(axis=1)  # (m+1, N2)
        cross = np.einsum("ind,nd->id", np.matmul(w, xi2), xi1)
        sq = rows @ (xi1 * xi1) + cols @ (xi2 * xi2) - 2.0 * cross  # (m+1, b)
        grad_ls = sq * self._inv_ls ** 2
        return np.concatenate([grad_ls.ravel(), grad_var])

    def grad_diag_contract(self, g: np.ndarray, ub: np.ndarray) -> np.ndarray:
        """``sum_n g[n] d k(x_n, x_n) / dtheta``: (n_params,) (lengthscales do not enter)."""
        grad_var = ((ub * ub).T @ g) * self._var
        return np.concatenate([np.zeros(self._n_comp * self._b), grad_var])

    # ----------------------------------------------------------------- init
    @classmethod
    def from_data(cls, xi, u, z) -> ADPKernel:
        """Heuristic initialisation from data.

        Lengthscales: ``sqrt(b) * std(xi_d)`` (typical scaled squared distance ~ 2), the same
        for every component. Variances: ``var(z) / ((m+1) mean(ubar_i^2))`` so that the prior
        variance at the data roughly matches ``var(z)``, each component taking an equal share.
        """
        xi, u, z = check_batch(xi, u, z)
        b = xi.shape[1]
        m = u.shape[1]
        std = xi.std(axis=0) if xi.shape[0] > 1 else np.ones(b)
        std = np.where(std > 1e-12, std, 1.0)
        ls = np.tile(np.sqrt(b) * std, (m + 1, 1))
        vz = float(np.var(z)) if z.shape[0] > 1 else 0.0
        if not vz > 1e-12:
            vz = max(float(np.mean(z * z)), 1.0)
        ub = ubar(u)
        msq = np.mean(ub * ub, axis=0)
        msq = np.where(msq > 1e-12, msq, 1.0)
        var = vz / ((m + 1) * msq)
        return cls(ls, var)
