"""AFVSGP: adaptive forgetting variational sparse GP (paper section III, eqs. 20-32).

State after ``fit`` and any number of ``update`` calls is the weighted Titsias posterior
over the last ``window`` samples with weights ``forgetting**age`` (newest 1):

    S = K_ox Lambda K_xo,   r = K_ox Lambda z,   B = (K_oo + S / s2)^-1        (eq. 20)

Per step (eqs. 25-26 as corrected in docs/equations.md), with ``k`` the sample's row of K_xo:

    S <- phi S + k_new k_new' - phi^P k_old k_old',   r <- phi r + z_new k_new - phi^P z_old k_old

(``k_old`` of the sample leaving the window, stored when it arrived). ``K_oo + S/s2`` is
refactored lazily at the next prediction; S and r are rebuilt from the stored window rows every
``refresh_every`` updates to bound round-off drift.

Inducing set (``adapt_inducing=True``):

- add rule (eq. 27, for the new sample, weight 1): the residual prior variance
  ``d = k_nn - k_no K_oo^-1 k_on`` must exceed ``add_threshold * k_nn`` (relative to the prior
  variance) and the noise variance ``s2``; otherwise the point adds nothing the inducing set
  cannot already explain above the noise. ``d`` near 0 also guards against duplicates.
- below ``num_inducing`` points a candidate is appended; at ``num_inducing`` the removal rule
  (eq. 28) is evaluated on the enlarged set: removing point j raises the weighted trace term of
  eq. 27 (``sum lambda (k_tt - Q_tt)``) by exactly ``[K^-1 S K^-1]_jj / [K^-1]_jj`` (eq. 28 with
  the other points accounted for). The least informative old point is replaced only if the
  new point's score exceeds it by ``swap_margin * k_nn``: the new sample is in the window, so
  its own ``k_nn`` would otherwise favour it over equally good old points and the set would
  churn on a stationary stream; with the margin it settles.

Hyperparameters are learned offline in ``fit`` by maximising the weighted bound (eq. 23) plus a
weak prior (:mod:`afvsgp_gym.gp.hyper`) with L-BFGS-B on the (last ``window``) fit samples, then
frozen online, as in the paper. The streaming state is an
:class:`~afvsgp_gym.gp.afvsgp_bank.AFVSGPBank` of one learner: the safety filter stacks the
fitted learners of its barriers into one bank.
"""

from __future__ import annotations

import math

import numpy as np

from afvsgp_gym.gp._base import BaseLearner, SparseLearner
from afvsgp_gym.gp._linalg import (
    DEFAULT_JITTER,
    check_batch,
    check_count,
    check_matrix,
    check_real,
    jittered_cholesky,
    ubar,
)
from afvsgp_gym.gp._sparse import greedy_inducing
from afvsgp_gym.gp.afvsgp_bank import AFVSGPBank, BankSettings, FittedState
from afvsgp_gym.gp.hyper import DEFAULT_PRIOR, LogNormalPrior
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["AFVSGP"]

_F64 = np.dtype(np.float64)


class AFVSGP(SparseLearner):
    """Adaptive forgetting VSGP with the ADP kernel (the paper's method).

    Parameters
    ----------
    kernel : ADPKernel or None
        Initial kernel (copied); None initialises from the data in ``fit``.
    noise_variance : float or None
        Initial noise variance; None uses ``0.1 var(z)``.
    num_inducing : int
        Maximum number of inducing points M.
    window : int
        Sliding window length P.
    forgetting : float
        Forgetting factor phi in (0, 1]; sample weights ``phi**age``.
    inducing : tuple (xi_o (M0, b), u_o (M0, m)) or None
        Initial inducing set; None selects ``num_inducing`` fit samples (pivoted Cholesky).
    adapt_inducing : bool
        False freezes the inducing set.
    add_threshold : float
        eq. 27 threshold, relative to the new sample's prior variance (see module docstring).
    swap_margin : float
        Replacement margin, in units of the new sample's prior variance.
    refresh_every : int or None
        Rebuild S and r from the window every this many updates (None: ``window``).
    jitter : float
        Relative jitter on K_oo (:func:`~afvsgp_gym.gp._linalg.jitter_for`); the absolute
        value ``jitter_`` is fixed at ``fit`` and used for inducing points added later.
    max_iter : int
        L-BFGS-B iterations per offline hyperparameter fit.
    prior : LogNormalPrior or None
        Weak prior on the log kernel parameters, centred at the initial kernel
        (:mod:`afvsgp_gym.gp.hyper`); None maximises the bound alone.

    Attributes
    ----------
    kernel_, noise_variance_, jitter_, inducing_xi_, inducing_u_, S_, r_, B_, n_seen_,
    n_added_, n_removed_
    bound_ : float
        Weighted bound (eq. 23) of the fit window at the fitted hyperparameters on the inducing
        set the learner starts streaming with (``fit``'s final set), with ``jitter_``.
    """

    def __init__(self, kernel: ADPKernel | None = None, noise_variance: float | None = None,
                 num_inducing: int = 20, window: int = 200, forgetting: float = 0.99,
                 inducing=None, adapt_inducing: bool = True, add_threshold: float = 0.1, *,
                 swap_margin: float = 1.0, refresh_every: int | None = None,
                 jitter: float = DEFAULT_JITTER, max_iter: int = 200,
                 prior: LogNormalPrior | None = DEFAULT_PRIOR):
        self.kernel = kernel
        self.noise_variance = noise_variance
        self.num_inducing = num_inducing
        self.window = window
        self.forgetting = forgetting
        self.inducing = inducing
        self.adapt_inducing = adapt_inducing
        self.add_threshold = add_threshold
        self.swap_margin = swap_margin
        self.refresh_every = refresh_every
        self.jitter = jitter
        self.max_iter = max_iter
        self.prior = prior

    # ------------------------------------------------------------------ fit
    def _check_params(self) -> None:
        super()._check_params()
        check_count(self.num_inducing, "num_inducing")
        check_count(self.window, "window")
        check_real(self.forgetting, "forgetting", low=0.0, high=1.0, low_open=True)
        check_real(self.add_threshold, "add_threshold", low=0.0)
        check_real(self.swap_margin, "swap_margin", low=0.0)
        if self.refresh_every is not None:
            check_count(self.refresh_every, "refresh_every")
        check_real(self.jitter, "jitter", low=0.0)
        check_count(self.max_iter, "max_iter")

    def fit(self, xi, u, z, learn_hyperparameters: bool = True) -> AFVSGP:
        """Fit on the first samples (chronological rows; the last ``window`` are kept) and
        learn hyperparameters by maximising the weighted bound (eq. 23) plus the prior."""
        self._check_params()
        xi, u, z = check_batch(xi, u, z)
        p = int(self.window)
        xi, u, z = xi[-p:], u[-p:], z[-p:]
        weights = float(self.forgetting) ** np.arange(len(z) - 1, -1, -1, dtype=float)
        kernel, noise, xo, uo, jitter, bound = self._fit_hyperparameters(
            xi, u, z, weights, learn_hyperparameters)
        self.kernel_ = kernel
        self.noise_variance_ = noise
        self.jitter_ = jitter
        self.bound_ = bound
        settings = BankSettings(p, float(self.forgetting), int(self.num_inducing),
                                float(self.add_threshold), float(self.swap_margin),
                                None if self.refresh_every is None else int(self.refresh_every),
                                bool(self.adapt_inducing))
        state = FittedState(kernel, noise, jitter, xo, ubar(uo), xi, ubar(u), z)
        self._bank = AFVSGPBank(settings, [state])
        return self

    def _initial_inducing(self, kernel, xi, u):
        if self.inducing is not None:
            xo, uo = self.inducing
            xo, uo, _ = check_batch(xo, uo, input_dim=xi.shape[1], action_dim=u.shape[1])
            if len(xo) > int(self.num_inducing):
                raise ValueError(f"inducing has {len(xo)} points, more than num_inducing="
                                 f"{self.num_inducing}")
            return xo, uo
        idx = greedy_inducing(kernel, xi, u, int(self.num_inducing))
        return xi[idx], u[idx]

    # ------------------------------------------------------------------ stream
    def _fitted_bank(self) -> AFVSGPBank:
        try:
            return self._bank
        except AttributeError:
            raise RuntimeError("AFVSGP is not fitted; call fit first") from None

    def update(self, xi, u, z) -> AFVSGP:
        """Stream one sample (eqs. 24-28); O(M^2) plus O(P M) on inducing changes. A sample
        with NaN, inf or a wrong shape raises ``ValueError`` naming it; nothing changes."""
        bank = self._fitted_bank()
        xi = check_matrix(xi, "xi", ndim=1, nrows=bank.input_dim)
        u = check_matrix(u, "u", ndim=1, nrows=bank.action_dim)
        z = check_matrix(z, "z", ndim=0)
        if not math.isfinite(float(xi @ xi + u @ u + z * z)):
            raise ValueError("xi, u, z are too large (overflow)")
        bank.update(xi[None], u, z[None])
        return self

    def predict_affine(self, xi):
        """``b`` (N, m+1), ``Sigma`` (N, m+1, m+1): mean ``b . ubar``, var ``ubar' Sigma ubar``
        (eq. 20)."""
        self._fitted_bank()
        return BaseLearner.predict_affine(self, xi)

    def _predict_affine(self, xi):
        if xi.shape[0] == 1:  # the per-control-step path
            return self._bank.predict_affine(xi, np.zeros(1, dtype=int))
        return self._bank.predict_points(0, xi)

    _predict = BaseLearner._predict  # through the affine form

    # ------------------------------------------------------------------ fitted attributes
    def _m(self) -> int:
        return int(self._fitted_bank().n_inducing_[0])

    @property
    def inducing_xi_(self) -> np.ndarray:
        """(M, b) inducing features (copy)."""
        return self._fitted_bank()._ind_xi[0, : self._m()].copy()

    @property
    def inducing_u_(self) -> np.ndarray:
        """(M, m) inducing actions (copy)."""
        return self._fitted_bank()._ind_ub[0, : self._m(), 1:].copy()

    @property
    def S_(self) -> np.ndarray:
        """(M, M) ``K_ox Lambda K_xo`` (copy)."""
        bank, m = self._fitted_bank(), self._m()
        return bank._stats[0, :m, 1 : m + 1] / bank._scale[0]

    @property
    def r_(self) -> np.ndarray:
        """(M,) ``K_ox Lambda z`` (copy)."""
        bank, m = self._fitted_bank(), self._m()
        return bank._stats[0, :m, 0] / bank._scale[0]

    @property
    def B_(self) -> np.ndarray:
        """(M, M) ``(K_oo + S/s2)^-1`` (a dense copy for diagnostics; predictions use the
        factors)."""
        bank, m = self._fitted_bank(), self._m()
        low = jittered_cholesky(bank._koo[0, :m, :m] + self.S_ / self.noise_variance_,
                                name="K_oo + S/s2")
        inv = np.linalg.solve(low, np.eye(m))
        return inv.T @ inv

    @property
    def _l_oo(self) -> np.ndarray:
        """(M, M) ``chol(K_oo)`` (jitter included)."""
        return self._fitted_bank()._l_oo[0, : self._m(), : self._m()]

    @property
    def n_seen_(self) -> int:
        return int(self._fitted_bank().n_seen_[0])

    @property
    def n_added_(self) -> int:
        return int(self._fitted_bank().n_added_[0])

    @property
    def n_removed_(self) -> int:
        return int(self._fitted_bank().n_removed_[0])

    def window_samples(self):
        """Current window, oldest first: xi (n, b), u (n, m), z (n,), weights phi**age (n,)."""
        bank = self._fitted_bank()
        cnt, head, p = int(bank._count[0]), int(bank._head[0]), bank.window
        order = (head + 1 + np.arange(cnt)) % p if cnt == p else np.arange(cnt)
        return (bank._wxt[0][:, order].T.copy(), bank._wubt[0][1:, order].T.copy(),
                bank._wz[0, order].copy(), bank._weights(0)[order])
