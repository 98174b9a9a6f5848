"""VSGP: Titsias (2009) collapsed variational sparse GP with a fixed inducing set (paper
eqs. 14-18); the paper's non-adaptive baseline. ``update`` appends the sample and refreshes the
posterior over all data seen from the stored kernel rows (O(N M^2), no forgetting), in the
whitened form from the data (:meth:`WhitenedPosterior.from_data`)."""

from __future__ import annotations

import numpy as np

from afvsgp_gym.gp._base import SparseLearner
from afvsgp_gym.gp._linalg import (
    DEFAULT_JITTER,
    check_batch,
    check_count,
    check_real,
    check_sample,
    ubar,
)
from afvsgp_gym.gp._sparse import greedy_inducing
from afvsgp_gym.gp.bound import WhitenedPosterior
from afvsgp_gym.gp.hyper import DEFAULT_PRIOR, LogNormalPrior
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["VSGP"]


class VSGP(SparseLearner):
    """Variational sparse GP with the ADP kernel and a fixed inducing set.

    Parameters
    ----------
    kernel : ADPKernel or None
        Initial kernel (copied); None initialises from the data in ``fit``.
    noise_variance : float or None
        Initial noise variance; None uses ``0.1 var(z)``.
    num_inducing : int
        Number of inducing points chosen from the fit data (pivoted Cholesky) when
        ``inducing`` is None.
    inducing : tuple (xi_o (M, b), u_o (M, m)) or None
        Fixed inducing set.
    jitter : float
        Relative jitter on K_oo (:func:`~afvsgp_gym.gp._linalg.jitter_for`).
    max_iter : int
        L-BFGS-B iterations per hyperparameter fit.
    prior : LogNormalPrior or None
        Weak prior on the log kernel parameters, centred at the initial kernel
        (:mod:`afvsgp_gym.gp.hyper`); None maximises the bound alone.

    Attributes
    ----------
    kernel_, noise_variance_, jitter_ (absolute), inducing_xi_, inducing_u_, S_, r_, B_,
    n_seen_
    bound_ : float
        Titsias bound (eq. 18) of the fit data at the fitted hyperparameters on the final
        inducing set (the one the learner keeps), with ``jitter_``.
    """

    def __init__(self, kernel: ADPKernel | None = None, noise_variance: float | None = None, *,
                 num_inducing: int = 20, inducing=None, jitter: float = DEFAULT_JITTER,
                 max_iter: int = 200, prior: LogNormalPrior | None = DEFAULT_PRIOR):
        self.kernel = kernel
        self.noise_variance = noise_variance
        self.num_inducing = num_inducing
        self.inducing = inducing
        self.jitter = jitter
        self.max_iter = max_iter
        self.prior = prior

    def _check_params(self) -> None:
        super()._check_params()
        check_count(self.num_inducing, "num_inducing")
        check_real(self.jitter, "jitter", low=0.0)
        check_count(self.max_iter, "max_iter")

    def fit(self, xi, u, z, learn_hyperparameters: bool = True) -> VSGP:
        """Fit on (xi (N,b), u (N,m), z (N,)); maximises the Titsias bound (eq. 18) plus the
        prior over the hyperparameters unless ``learn_hyperparameters`` is False."""
        self._check_params()
        xi, u, z = check_batch(xi, u, z)
        kernel, noise, xo, uo, jitter, bound = self._fit_hyperparameters(
            xi, u, z, np.ones(len(z)), learn_hyperparameters)
        self.kernel_ = kernel
        self.noise_variance_ = noise
        self.jitter_ = jitter
        self.bound_ = bound
        self._setup_inducing(xo, ubar(uo), len(xo))
        n = len(z)
        cap = max(2 * n, 64)
        self._kxo = np.zeros((cap, len(xo)))
        self._z = np.zeros(cap)
        self._kxo[:n] = kernel._gram(xi, ubar(u), xo, ubar(uo))
        self._z[:n] = z
        self.n_seen_ = n
        self._dirty = True
        return self

    def _initial_inducing(self, kernel, xi, u):
        if self.inducing is not None:
            xo, uo = self.inducing
            xo, uo, _ = check_batch(xo, uo, input_dim=xi.shape[1], action_dim=u.shape[1])
            return xo, uo
        idx = greedy_inducing(kernel, xi, u, int(self.num_inducing))
        return xi[idx], u[idx]

    def _refresh_posterior(self) -> None:
        n = self.n_seen_
        self._post = WhitenedPosterior.from_data(self._l_oo, self._kxo[:n], self._z[:n], 1.0,
                                                 self.noise_variance_)
        self._dirty = False

    @property
    def S_(self) -> np.ndarray:
        """(M, M) ``K_ox K_xo`` over all data seen."""
        k = self._kxo[: self.n_seen_]
        return k.T @ k

    @property
    def r_(self) -> np.ndarray:
        """(M,) ``K_ox z`` over all data seen."""
        return self._kxo[: self.n_seen_].T @ self._z[: self.n_seen_]

    def update(self, xi, u, z) -> VSGP:
        """Append one sample and refresh the posterior over all data seen."""
        self._check_fitted()
        b, m = self._dims()
        xi, u, z = check_sample(xi, u, z, input_dim=b, action_dim=m)
        ub = np.concatenate([[1.0], u])
        k_new = ub @ self._ind.kt(xi)
        n = self.n_seen_
        if n == self._kxo.shape[0]:
            self._kxo = np.concatenate([self._kxo, np.zeros_like(self._kxo)])
            self._z = np.concatenate([self._z, np.zeros_like(self._z)])
        self._kxo[n] = k_new
        self._z[n] = z
        self.n_seen_ = n + 1
        self._refresh_posterior()
        return self
