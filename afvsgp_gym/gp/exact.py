"""ExactGP: full GP with the ADP kernel (Castaneda et al. 2021), the paper's offline "GP"
baseline. Hyperparameters maximise the log marginal likelihood plus the learners' weak prior
(:mod:`afvsgp_gym.gp.hyper`, analytic gradients); ``update`` appends a sample by a Cholesky row
append (O(N^2)) unless ``online=False``."""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from afvsgp_gym.gp._base import BaseLearner
from afvsgp_gym.gp._linalg import (
    check_batch,
    check_count,
    check_sample,
    jittered_cholesky,
    ubar,
)
from afvsgp_gym.gp.hyper import DEFAULT_PRIOR, LogNormalPrior, maximise, noise_box, theta_box
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["ExactGP", "log_marginal_likelihood"]


def log_marginal_likelihood(params, kernel: ADPKernel, xi, u, z):
    """``log N(z | 0, K + s2 I)`` and its gradient w.r.t. ``concat(theta, [log s2])``.

    ``kernel`` is modified (its theta set to ``params[:-1]``). Rasmussen & Williams eq. 5.9.
    """
    kernel.theta = params[:-1]
    s2 = float(np.exp(params[-1]))
    ub = ubar(u)
    k = kernel._gram(xi, ub)
    k[np.diag_indices_from(k)] += s2
    low = jittered_cholesky(k, name="K + s2 I")
    alpha = cho_solve((low, True), z, check_finite=False)
    n = len(z)
    val = -0.5 * z @ alpha - np.sum(np.log(np.diag(low))) - 0.5 * n * np.log(2 * np.pi)
    g = 0.5 * (np.outer(alpha, alpha) - cho_solve((low, True), np.eye(n), check_finite=False))
    grad = kernel.grad_contract(g, xi, ub)
    return float(val), np.concatenate([grad, [np.trace(g) * s2]])


class ExactGP(BaseLearner):
    """Full GP regression with the ADP kernel.

    Parameters
    ----------
    kernel : ADPKernel or None
        Initial kernel (copied); None initialises from the data in ``fit``.
    noise_variance : float or None
        Initial noise variance; None uses ``0.1 var(z)``.
    online : bool
        True: ``update`` appends the sample (Cholesky row append). False: the offline
        baseline; ``update`` validates its input and leaves the posterior unchanged.
    max_iter : int
        L-BFGS-B iterations for the hyperparameters.
    prior : LogNormalPrior or None
        Weak prior on the log kernel parameters, centred at the initial kernel; None
        maximises the marginal likelihood alone.

    Attributes
    ----------
    kernel_, noise_variance_, xi_train_, u_train_, z_train_, L_ (lower chol of K + s2 I),
    alpha_, log_marginal_likelihood_value_
    """

    def __init__(self, kernel: ADPKernel | None = None, noise_variance: float | None = None, *,
                 online: bool = True, max_iter: int = 200,
                 prior: LogNormalPrior | None = DEFAULT_PRIOR):
        self.kernel = kernel
        self.noise_variance = noise_variance
        self.online = online
        self.max_iter = max_iter
        self.prior = prior

    def _check_params(self) -> None:
        super()._check_params()
        check_count(self.max_iter, "max_iter")

    def fit(self, xi, u, z, learn_hyperparameters: bool = True) -> ExactGP:
        """Fit on (xi (N,b), u (N,m), z (N,)), maximising the log marginal likelihood plus the
        prior unless ``learn_hyperparameters`` is False."""
        self._check_params()
        xi, u, z = check_batch(xi, u, z)
        kernel, noise = self._init_hyper(xi, u, z)
        if learn_hyperparameters:
            center = kernel.theta
            nl = kernel.n_components * kernel.input_dim
            work = kernel.clone()
            prior = self.prior

            def evidence(p):
                val, grad = log_marginal_likelihood(p, work, xi, u, z)
                if prior is not None:
                    lp, glp = prior.log_density(p[:-1], center, nl)
                    val += lp
                    grad[:-1] += glp
                return val, grad

            best, _ = maximise(evidence, np.concatenate([center, [np.log(noise)]]),
                               theta_box(center) + [noise_box(z)], self.max_iter)
            kernel = kernel.with_theta(best[:-1])
            noise = float(np.exp(best[-1]))
        self.kernel_ = kernel
        self.noise_variance_ = noise
        self.xi_train_, self.u_train_, self.z_train_ = xi, u, z
        self._ub = ubar(u)
        k = kernel._gram(xi, self._ub)
        k[np.diag_indices_from(k)] += noise
        self.L_ = jittered_cholesky(k, name="K + s2 I")
        self._refresh_alpha()
        return self

    def _refresh_alpha(self) -> None:
        self.alpha_ = cho_solve((self.L_, True), self.z_train_, check_finite=False)
        self.log_marginal_likelihood_value_ = float(
            -0.5 * self.z_train_ @ self.alpha_ - np.sum(np.log(np.diag(self.L_)))
            - 0.5 * len(self.z_train_) * np.log(2 * np.pi))

    def update(self, xi, u, z) -> ExactGP:
        """Append one sample: ``L <- [[L, 0], [l', d]]``, ``l = L^-1 k``, ``d^2 = k** + s2 - l'l``.
        """
        self._check_fitted()
        b, m = self._dims()
        xi, u, z = check_sample(xi, u, z, input_dim=b, action_dim=m)
        if not self.online:
            return self
        ub = np.concatenate([[1.0], u])[None, :]
        k_new = self.kernel_._gram(self.xi_train_, self._ub, xi[None, :], ub)[:, 0]
        kss = float(self.kernel_._diag(ub)[0]) + self.noise_variance_
        l_row = solve_triangular(self.L_, k_new, lower=True, check_finite=False)
        d2 = kss - l_row @ l_row
        n = self.L_.shape[0]
        if d2 <= 1e-12 * kss:  # numerically dependent: refactor with jitter
            xi_all = np.vstack([self.xi_train_, xi[None, :]])
            ub_all = np.vstack([self._ub, ub])
            k = self.kernel_._gram(xi_all, ub_all)
            k[np.diag_indices_from(k)] += self.noise_variance_
            low = jittered_cholesky(k, name="K + s2 I")
        else:
            low = np.zeros((n + 1, n + 1))
            low[:n, :n] = self.L_
            low[n, :n] = l_row
            low[n, n] = np.sqrt(d2)
        self.L_ = low
        self.xi_train_ = np.vstack([self.xi_train_, xi[None, :]])
        self.u_train_ = np.vstack([self.u_train_, u[None, :]])
        self._ub = np.vstack([self._ub, ub])
        self.z_train_ = np.append(self.z_train_, z)
        self._refresh_alpha()
        return self

    def _predict_affine(self, xi):
        kt = self.kernel_._cross_affine(xi, self.xi_train_, self._ub)  # [N*, m+1, N]
        bvec = kt @ self.alpha_
        v = solve_triangular(self.L_, kt.reshape(-1, kt.shape[2]).T, lower=True,
                             check_finite=False)  # [N, N* (m+1)]
        v = v.T.reshape(kt.shape)
        sig = -np.matmul(v, v.transpose(0, 2, 1))
        idx = np.arange(kt.shape[1])
        sig[:, idx, idx] += self.kernel_._var
        return bvec, 0.5 * (sig + sig.transpose(0, 2, 1))

    def _predict(self, xi, u):
        ub = ubar(u)
        ks = self.kernel_._gram(xi, ub, self.xi_train_, self._ub)  # [N*, N]
        v = solve_triangular(self.L_, ks.T, lower=True, check_finite=False)
        return ks @ self.alpha_, self.kernel_._diag(ub) - np.einsum("ij,ij->j", v, v)
