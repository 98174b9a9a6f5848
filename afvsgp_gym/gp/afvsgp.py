"""AFVSGP: adaptive forgetting variational sparse GP (paper section III, eqs. 20-32).

State after ``fit`` and any number of ``update`` calls is the weighted Titsias posterior
over the last ``window`` samples with weights ``forgetting**age`` (newest 1):

    S = K_ox Lambda K_xo,   r = K_ox Lambda z,   B = (K_oo + S / s2)^-1        (eq. 20)

Per step (DESIGN's corrected eqs. 25-26), with ``k`` the sample's row of K_xo:

    S <- phi S + k_new k_new' - phi^P k_old k_old',   r <- phi r + z_new k_new - phi^P z_old k_old

(``k_old`` of the sample leaving the window, stored when it arrived). ``B^-1 = K_oo + S/s2`` is
refactored lazily at the next prediction (M = 20: a few microseconds); S and r are rebuilt from
the stored window rows every ``refresh_every`` updates to bound round-off drift.

Per-step cost is Python/LAPACK call overhead, not flops, so the step is a short fixed sequence of
calls on preallocated buffers: the kernel row of a point is one product on ``[xi, ubar, xi^2,
ubar^2]``; the one-point ``predict_affine`` is one factorisation, one triangular solve and two
``syrk`` Grams (``_predict_one``); an ``update`` at the point of the last one-point prediction
reuses that prediction's kernel row (bit-identical to recomputing it).

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
- chol(K_oo) is appended (O(M^2)) on add and rank-one updated (O(M^2)) on removal.

Hyperparameters are learned offline in ``fit`` by maximising the weighted bound (eq. 23) plus a
weak prior (:mod:`afvsgp_gym.gp.hyper`) with L-BFGS-B on the (last ``window``) fit samples, then
frozen online, as in the paper.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg.blas import dger, dtrsm
from scipy.linalg.lapack import dpotrf, dtrtri, dtrtrs

from afvsgp_gym.gp._base import SparseLearner
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
from afvsgp_gym.gp.hyper import DEFAULT_PRIOR, LogNormalPrior
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["AFVSGP"]

_F64 = np.dtype(np.float64)


def _chol_delete(low: np.ndarray, j: int) -> np.ndarray:
    """Cholesky factor of K with row/column j removed, from chol(K): O(M^2) rank-one update
    of the trailing block (L33 L33' + l32 l32')."""
    n = low.shape[0]
    out = np.delete(np.delete(low, j, axis=0), j, axis=1)
    x = low[j + 1:, j].copy()
    sub = out[j:, j:]  # view of the trailing block
    for k in range(n - 1 - j):
        lkk = sub[k, k]
        rad = math.hypot(lkk, x[k])
        c, s = rad / lkk, x[k] / lkk
        sub[k, k] = rad
        if k + 1 < n - 1 - j:
            col = sub[k + 1:, k]
            col += s * x[k + 1:]
            col /= c
            x[k + 1:] = c * x[k + 1:] - s * col
    return out


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
        n = len(z)
        phi = float(self.forgetting)
        weights = phi ** np.arange(n - 1, -1, -1, dtype=float)
        kernel, noise, xo, uo, jitter, bound = self._fit_hyperparameters(
            xi, u, z, weights, learn_hyperparameters)
        self.kernel_ = kernel
        self.noise_variance_ = noise
        self.jitter_ = jitter
        self.bound_ = bound
        self._cap = max(int(self.num_inducing), len(xo)) + 1
        b, c = kernel.input_dim, kernel.n_components
        # Sample rows [z, k(x, o_1..o_cap), xi, ubar, xi^2, ubar^2]: the window ring buffer
        # (slot `_head` holds the newest sample) and the update's scratch row share this layout,
        # so a step stores its sample with one copy. ``ubar^2[0] = 1`` is the constant of the
        # kernel-row product (see ``_setup_row_kernel``).
        o = self._cap + 1
        nf = 2 * (b + c)
        self._row = np.zeros(o + nf)
        self._row[o + b] = self._row[o + 2 * b + c] = 1.0
        self._sl_xi = slice(o, o + b)
        self._sl_u = slice(o + b + 1, o + b + c)
        self._feat0 = self._row[o:].copy()  # clean features (ubar = e_0)
        self._wbuf = np.zeros((p, o + nf))
        self._bind_row_views()
        self._ones_f = np.ones(b + c)
        self._var = kernel._var
        self._one_shape = (1, b)
        self._shapes = ((b,), (c - 1,))
        self._nc = c
        self._setup_inducing(xo, ubar(uo), self._cap)
        self._p = p
        self._phi = phi
        self._phi_p = phi ** p
        self._pow = phi ** np.arange(p, dtype=float)
        ub_fit = ubar(u)
        self._win[:n, 0] = z
        self._win[:n, 1:len(xo) + 1] = kernel._gram(xi, ub_fit, xo, ubar(uo))
        self._win_xi[:n] = xi
        self._win_ub[:n] = ub_fit
        self._win_feat[:n, b + c:] = self._win_feat[:n, :b + c] ** 2
        # window-column product for inducing candidates (``_window_column``)
        self._gcol = np.zeros((nf, c))
        self._gcol[b + c:2 * b + c] = -0.5 * self._ind.inv_ls2.T
        self._inv_phi = 1.0 / phi
        self._count = n
        self._head = n - 1
        self._refresh_every = p if self.refresh_every is None else int(self.refresh_every)
        self._since_refresh = 0
        self.n_seen_ = n
        self.n_added_ = 0
        self.n_removed_ = 0
        self._rebuild_stats()
        return self

    # ------------------------------------------------------------------ buffer views
    _VIEWS = ("_feat", "_feat1", "_feat2", "_ub_row", "_xi2_row", "_ub2_row", "_win",
              "_win_feat", "_win_xi", "_win_ub", "_e2", "_k_row", "_y_row", "_rhs", "_rhs_ktT",
              "_scaled", "_sig")

    def _bind_row_views(self) -> None:
        """Views of the sample row ``[z, k(cap), xi, ubar, xi^2, ubar^2]`` and the window."""
        b, c = self.kernel_.input_dim, self.kernel_.n_components
        o = self._cap + 1
        row = self._row
        self._feat = row[o:]  # [xi, ubar, xi^2, ubar^2]
        self._feat1 = row[o:o + b + c]
        self._feat2 = row[o + b + c:]
        self._ub_row = row[o + b:o + b + c]
        self._xi2_row = row[o + b + c:o + 2 * b + c]
        self._ub2_row = row[o + 2 * b + c:]
        win = self._wbuf
        self._win = win[:, :o]
        self._win_feat = win[:, o:]
        self._win_xi = win[:, o:o + b]
        self._win_ub = win[:, o + b:o + b + c]

    def _bind_kernel_views(self) -> None:
        """Views that depend on the inducing-set size M (see ``_setup_row_kernel``)."""
        c = self.kernel_.n_components
        m = self._ind.M
        self._e2 = self._e.reshape(c, m)
        self._k_row = self._row[1:m + 1]
        self._y_row = self._row[:m + 1]
        work = self._work
        self._rhs = work[:, :c + 1]
        self._rhs_ktT = work[:, :c].T
        self._scaled = work[:, c:]
        self._sig = work[:, c + 1:]

    def __getstate__(self) -> dict:
        """Pickle/deepcopy without the buffer views (copies would lose the aliasing)."""
        state = self.__dict__.copy()
        for name in self._VIEWS:
            state.pop(name, None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if "_row" in state:  # fitted: rebind the views onto the copied buffers
            self._bind_row_views()
            self._bind_kernel_views()
            ind = self._ind
            ind._a = ind.xs2.reshape(-1, ind.xs2.shape[2])  # InducingCache's gemv view

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

    def _weights(self) -> np.ndarray:
        """Weights phi**age of window slots [0, count)."""
        ages = (self._head - np.arange(self._count)) % self._p
        return self._pow[ages]

    def _rebuild_stats(self) -> None:
        """S and r from the stored window rows (the periodic drift refresh)."""
        m = self._ind.M
        rows = self._win[: self._count, : m + 1]
        wk = rows[:, 1:] * self._weights()[:, None]
        self._stats = np.asfortranarray(wk.T @ rows)  # [K' Lambda z, K' Lambda K]
        self._scale = 1.0
        self._since_refresh = 0
        self._dirty = self._fdirty = True

    def _renormalise(self) -> None:
        if self._scale != 1.0:
            self._stats *= 1.0 / self._scale
            self._scale = 1.0

    # ------------------------------------------------------------------ update
    def update(self, xi, u, z) -> AFVSGP:
        """Stream one sample (eqs. 24-28); O(M^2) plus O(P M) on inducing changes.

        The per-step path is a fixed, short sequence of BLAS/ufunc calls on preallocated
        buffers: one product gives the kernel row's exponents, two rank-one updates (``dger``)
        slide the window. When ``xi`` is the point of the last one-point ``predict_affine``
        (the filter predicts at ``xi_t``, then learns from ``(xi_t, u_t, z_t)``), the kernel
        row ``Kt`` that prediction computed (same inducing set, same arithmetic) is reused."""
        try:
            shape_xi, shape_u = self._shapes
        except AttributeError:
            raise RuntimeError("AFVSGP is not fitted; call fit first") from None
        if not (type(xi) is np.ndarray and xi.dtype is _F64 and xi.shape == shape_xi):
            xi = check_matrix(xi, "xi", ndim=1, nrows=shape_xi[0])
        if not (type(u) is np.ndarray and u.dtype is _F64 and u.shape == shape_u):
            u = check_matrix(u, "u", ndim=1, nrows=shape_u[0])
        try:
            zf = float(z)
        except (TypeError, ValueError):
            raise ValueError(f"z must be a finite scalar, got {z!r}") from None
        row = self._row  # scratch: [z, k_new, xi, ubar, xi^2, ubar^2]
        row[self._sl_u] = u
        ub = self._ub_row
        ub2 = self._ub2_row
        if xi.tobytes() == self._kt_key:  # Kt of this xi is in the prediction buffer
            np.multiply(ub, ub, out=ub2)
            kss = float(ub2.dot(self._var))  # sum_i s_i ubar_i^2, eq. 19
            if not math.isfinite(kss + zf):  # checks u and z (xi was checked in predict)
                self._reject(xi, u, zf)
            kt = self._rhs_ktT
        else:
            self._kt_key = None
            row[self._sl_xi] = xi
            sq = self._feat2
            np.multiply(self._feat1, self._feat1, out=sq)
            if not math.isfinite(sq.dot(self._ones_f) + zf):  # one check for xi, u and z
                self._reject(xi, u, zf)
            kss = float(ub2.dot(self._var))
            e = np.dot(self._amat, self._feat, out=self._e)  # log k_i(x, o_j)
            np.exp(e, out=e)
            kt = np.multiply(self._e2, self._ubt, out=self._kt_u)  # [m+1, M], eq. 21
        k_new = np.dot(ub, kt, out=self._k_row)
        row[0] = zf
        # sliding window with forgetting (DESIGN eqs. 25-26); phi S is folded into the scale
        scale = self._scale * self._inv_phi
        self._scale = scale
        stats = self._stats
        head = self._head
        if self._count == self._p:
            slot = head + 1 if head + 1 < self._p else 0
            old = self._wbuf[slot]
            stats = dger(-self._phi_p * scale, old[self._sl_k], old[self._sl_y], 1, 1, stats,
                         1, 1, 1)
        else:
            slot = self._count
            self._count = slot + 1
        self._stats = dger(scale, k_new, self._y_row, 1, 1, stats, 1, 1, 1)
        self._wbuf[slot] = row
        self._head = slot
        self.n_seen_ += 1
        self._dirty = self._fdirty = True
        self._since_refresh += 1
        if self._since_refresh >= self._refresh_every:
            self._rebuild_stats()
        elif scale > 1e100:
            self._renormalise()
        if self.adapt_inducing:
            d = kss - float(k_new.dot(self._koo_inv.dot(k_new)))  # eq. 27 residual, weight 1
            if (d > self.add_threshold * kss and d > self.noise_variance_
                    and d > 1e-6 * kss):
                lvec = dtrtrs(self._l_oo, k_new, lower=1)[0]  # L_oo^-1 k_new
                d = kss - float(lvec @ lvec)  # the same, from the factor (stable)
                if d > 1e-6 * kss:
                    self._consider_add(xi, ub.copy(), kss, k_new.copy(), lvec, d)
        return self

    def _reject(self, xi: np.ndarray, u: np.ndarray, z: float):
        """Raise the ValueError for a non-finite sample; clear the scratch row (the next
        prediction reads its features) so no state changes."""
        self._kt_key = None
        self._feat[:] = self._feat0
        for arr, name in ((xi, "xi"), (u, "u"), (np.array([z]), "z")):
            if not np.isfinite(arr).all():
                raise ValueError(f"{name} contains NaN or inf")
        raise ValueError("xi, u, z are too large (overflow)")

    # ------------------------------------------------------------------ one-point predictive
    def _setup_row_kernel(self) -> None:
        """Buffers of the per-step path for the current inducing set (rebuilt on changes).

        ``_amat`` ((m+1) M, 2(b+m+1)) times the features ``[xi, ubar, xi^2, ubar^2]`` gives
        the exponents
        ``log k_i(xi, o_j) = log s_i - |o_j/l_i|^2/2 + (o_j/l_i^2).xi - (1/(2 l_i^2)).xi^2``
        (the constant sits in the ``ubar_0^2 = 1`` column).
        """
        ind = self._ind
        m = ind.M
        b, c = self.kernel_.input_dim, self.kernel_.n_components
        nf = 2 * (b + c)
        a = np.zeros((c * m, nf))
        blk = a.reshape(c, m, nf)
        blk[:, :, :b] = ind.xs2[:, :m, :b]
        blk[:, :, b + c:2 * b + c] = ind.xs2[:, :m, b:2 * b]
        blk[:, :, 2 * b + c] = ind.xs2[:, :m, 2 * b]
        self._amat = a
        self._e = np.empty(c * m)
        self._ubt = ind.ubt[:, :m].copy()
        self._kt_u = np.empty((c, m))
        self._sl_k = slice(1, m + 1)
        self._sl_y = slice(0, m + 1)
        # one Fortran-order block [Kt', r/s2, K_oo + S/s2]: the last M columns are factored in
        # place, the first m+2 are the right-hand side (Kt (m+1, M) is its contiguous start);
        # [r/s2, S/s2] is one product with the [r, S] statistics
        self._work = np.zeros((m, c + 1 + m), order="F")
        self._bind_kernel_views()
        self._koo_f = np.asfortranarray(self._koo)  # same layout as _sig (cheaper sum)
        # L_oo^-T for the Nystroem term (refreshed with the inducing set; triangular inverse)
        linv, info = dtrtri(self._l_oo, lower=1)
        self._l_oo_invt = linv.T if info == 0 else np.linalg.inv(self._l_oo).T
        self._kt_key = None  # xi (bytes) whose Kt is in _rhs_ktT
        self._fdirty = True

    def _set_koo_chol(self, low: np.ndarray) -> None:
        super()._set_koo_chol(low)
        self._setup_row_kernel()

    def _refresh_factor(self) -> None:
        """``chol(K_oo + S/s2)`` and ``r/s2`` for one-point predictions."""
        st = self._stats
        inv_s = 1.0 / (self.noise_variance_ * self._scale)
        np.multiply(st, inv_s, out=self._scaled)  # [r/s2, S/s2]
        sig = self._sig
        sig += self._koo_f
        info = dpotrf(sig, 1, 0, 1)[1]  # in place, lower triangle
        if info != 0:
            sig = np.multiply(st[:, 1:], inv_s)
            sig += self._koo
            self._sig[:] = jittered_cholesky(sig, name="K_oo + S/s2")
        self._fdirty = False

    def _predict_one(self, x: np.ndarray):
        """``(b (1, m+1), Sigma (1, m+1, m+1))`` at one point (eq. 20), or None if ``x`` is
        not finite (or overflows ``|x|^2``).

        With ``L = chol(B^-1)`` and ``F = L^-1 [Kt', r/s2]``: ``F'F = [[Kt B Kt', b'], [b, .]]``;
        the Nystroem term ``Kt K_oo^-1 Kt' = G G'`` with ``G = Kt L_oo^-T``. Both Grams are
        BLAS ``syrk`` (exactly symmetric)."""
        if not math.isfinite(x.dot(x)):
            return None
        # features in the update's scratch row (its ubar part has zero weight here)
        self._row[self._sl_xi] = x
        np.multiply(x, x, out=self._xi2_row)
        e = np.dot(self._amat, self._feat, out=self._e)
        if self._fdirty:
            self._refresh_factor()
        np.exp(e, out=e)
        np.multiply(self._e2, self._ubt, out=self._rhs_ktT)  # Kt (m+1, M), eq. 21
        self._kt_key = x.tobytes()
        g = self._rhs_ktT.dot(self._l_oo_invt)
        f = dtrsm(1.0, self._sig, self._rhs, 0, 1, 0, 0, 0)
        ff = f.T.dot(f)
        c = self._nc
        sig = np.subtract(ff[:c, :c], g.dot(g.T))
        sig += self._ind.var_diag
        return ff[c:, :c], sig[None]

    def predict_affine(self, xi):
        """``b`` (N, m+1), ``Sigma`` (N, m+1, m+1): mean ``b . ubar``, var ``ubar' Sigma ubar``
        (eq. 20); one float64 point (the per-control-step call) takes a short fast path."""
        if (type(xi) is np.ndarray and xi.shape == getattr(self, "_one_shape", None)
                and xi.dtype is _F64):
            out = self._predict_one(xi[0])
            if out is not None:
                return out
        return super().predict_affine(xi)

    def _predict_affine(self, xi):
        if xi.shape[0] == 1:
            out = self._predict_one(xi[0])
            if out is not None:
                return out
        return super()._predict_affine(xi)

    # ------------------------------------------------------------------ inducing set
    def _consider_add(self, xi, ub, kss, k_new, lvec, d) -> None:
        """Add the newest sample as an inducing point (eqs. 29-30), replacing the least
        informative one (eq. 28) when the set is full."""
        self._renormalise()
        m = self._ind.M
        cnt = self._count
        col = self._window_column(xi, ub)  # k(window, o_new)
        lc = self._weights() * col
        # enlarged [r, S] (M+1, M+2): new row and column from the window (eq. 30)
        stats = np.empty((m + 1, m + 2), order="F")
        stats[:m, : m + 1] = self._stats
        stats[m, 1:m + 1] = stats[:m, m + 1] = lc @ self._win[:cnt, 1:m + 1]
        stats[m, 0] = lc @ self._win[:cnt, 0]
        stats[m, m + 1] = lc @ col
        # enlarged chol(K_oo) (row append, O(M^2)) and K_oo
        low = np.zeros((m + 1, m + 1))
        low[:m, :m] = self._l_oo
        low[m, :m] = lvec
        low[m, m] = math.sqrt(d + self.jitter_)
        koo = np.empty((m + 1, m + 1))
        koo[:m, :m] = self._koo
        koo[m, :m] = koo[:m, m] = k_new
        koo[m, m] = kss + self.jitter_
        drop = None
        if m + 1 > int(self.num_inducing):
            linv = dtrtri(low, lower=1)[0]
            kinv = linv.T @ linv
            score = np.einsum("ij,jk,ki->i", kinv, stats[:, 1:], kinv) / np.diag(kinv)
            j = int(np.argmin(score[:m]))  # eq. 28: least informative old point
            if score[m] - score[j] <= self.swap_margin * kss:
                return  # not informative enough: state unchanged
            drop = j
        # commit the addition
        self._ind.append(xi, ub)
        self._win[:cnt, m + 1] = col
        self._stats, self._koo = stats, koo
        self.n_added_ += 1
        if drop is None:
            self._set_koo_chol(low)
            return
        self._remove(drop, low)

    def _window_column(self, xi: np.ndarray, ub: np.ndarray) -> np.ndarray:
        """``k(x_t, (xi, ub))`` for the window samples with one (cnt, 2(b+m+1)) x (., m+1)
        product on the stored features:
        ``log k_i = log s_i - |xi/l_i|^2/2 + x_t.(xi/l_i^2) - x_t^2.(1/(2 l_i^2))``."""
        cnt = self._count
        inv_ls2 = self._ind.inv_ls2  # (m+1, b)
        b = inv_ls2.shape[1]
        g = self._gcol  # rows for ubar and ubar^2 stay zero
        g[:b] = (inv_ls2 * xi).T
        e = self._win_feat[:cnt] @ g
        e += self._ind.log_var - 0.5 * (inv_ls2 @ (xi * xi))
        np.minimum(e, self._ind.log_var, out=e)
        np.exp(e, out=e)
        e *= self._win_ub[:cnt]
        return e @ ub

    def _remove(self, j: int, low: np.ndarray) -> None:
        """Drop inducing point j (eq. 32): delete its row/column everywhere, O(P M)."""
        m = self._ind.M
        self._ind.delete(j)
        cnt = self._count
        self._win[:cnt, j + 1:m] = self._win[:cnt, j + 2:m + 1]
        keep = np.r_[0:j, j + 1:m]
        self._stats = np.asfortranarray(self._stats[np.ix_(keep, np.r_[0, keep + 1])])
        self._koo = self._koo[np.ix_(keep, keep)]
        self._set_koo_chol(_chol_delete(low, j))
        self.n_removed_ += 1

    # ------------------------------------------------------------------ diagnostics
    def window_samples(self):
        """Current window, oldest first: xi (n, b), u (n, m), z (n,), weights phi**age (n,)."""
        self._check_fitted()
        cnt = self._count
        order = (self._head + 1 + np.arange(cnt)) % cnt if cnt == self._p else np.arange(cnt)
        return (self._win_xi[order].copy(), self._win_ub[order, 1:].copy(),
                self._win[order, 0].copy(), self._weights()[order])
