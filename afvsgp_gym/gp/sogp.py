"""Streaming sparse GP (Bui, Nguyen and Turner 2017), collapsed VFE, with the ADP kernel.

The paper's "SOGP" baseline (Table I). Data arrive in batches ``f = (xi, u, z)``. The old
approximate posterior is carried as a Gaussian ``q_old(a) = N(m_a, S_a)`` over the old inducing
points ``a`` (prior ``K'_aa`` under the hyperparameters in force when it was formed). The new
posterior over new inducing points ``b`` maximises Bui's collapsed online bound (their eq. 6,
VFE case)::

    F = log N(yhat | 0, Khat + Sigmahat) - 1/(2 s2) tr(K_ff - Q_ff)
        - 1/2 tr(D_a^-1 (K_aa - Q_aa)) + Delta_a,
    yhat = [y; D_a S_a^-1 m_a],  Sigmahat = blkdiag(s2 I, D_a),  D_a^-1 = S_a^-1 - K'_aa^-1,
    Khat = [K_fb; K_ab] K_bb^-1 [K_bf, K_ba],  Q_aa = K_ab K_bb^-1 K_ba,
    Delta_a = 1/2 (log|K'_aa| - log|S_a| + log|D_a|) - 1/2 m_a' S_a^-1 m_a
              + 1/2 yhat_a' D_a^-1 yhat_a + M_a/2 log(2 pi)   (normalises q_old / p_old).

Its optimum is ``q(b) ~ p(b) exp(E_p(f|b)[log p(y|f) + log q_old(a)/p_old(a)])``. We never form
``S_a^-1 - K'_aa^-1`` (a difference of inverses): with ``L'`` = chol(K'_aa) and
``S_a = K' (K' + Phi_a)^-1 K'``, the state is kept whitened,

    Phit_a = L'^-1 Phi_a L'^-T,   rt_a = L'^-1 r_a,   so
    D_a^-1 = L'^-T Phit_a L'^-1,  S_a^-1 m_a = L'^-T rt_a,
    log|K'_aa| - log|S_a| = log|I + Phit_a|,   m_a' S_a^-1 m_a = rt_a' (I + Phit_a)^-1 rt_a.

One step, with ``L_b`` = chol(K_bb), ``A = L_b^-1 K_bf / s`` and ``G = L_b^-1 K_ba L'^-T``::

    Phit_b = A A' + G Phit_a G',   rt_b = A y / s + G rt_a,   D = I + Phit_b,
    q(b):  m_b = L_b D^-1 rt_b,  S_b = L_b D^-1 L_b'          (whitened Titsias form)
    F = -n/2 log(2 pi s2) - (y'y + sum k_ff)/(2 s2) + 1/2 |A|^2 + 1/2 rt_b' D^-1 rt_b
        - 1/2 log|D| + 1/2 log|I + Phit_a| - 1/2 rt_a' (I + Phit_a)^-1 rt_a
        - 1/2 tr(Phit_a (L'^-1 K_aa L'^-T - G'G)).

With no old points this is Titsias 2009 (paper eqs. 17-18). With ``b = a`` and unchanged
hyperparameters, ``G = I``: the information ``Phit`` and ``rt`` simply add up, so streaming
equals the batch posterior over all data (Bui et al.'s key property). Both, and the general
step against the dense formula above, are checked in tests/gp/test_sogp.py.

Jitter: the inducing variables are ``f(b) + e`` with ``var(e) = eps_b`` from the sparse learners'
policy (:func:`~afvsgp_gym.gp._linalg.jitter_for`); an old and a new inducing variable at the
same input share their jitter (covariance ``sqrt(eps_a eps_b)``), which keeps ``b = a`` exact.

Predictions (paper eqs. 14, 20-21) come from ``L_b``, ``Phit_b`` and ``rt_b`` through the sparse
learners' :class:`~afvsgp_gym.gp.bound.WhitenedPosterior` (``Phit`` and ``rt`` are its ``P``
and ``v``). No factor is inverted explicitly: ``L_b``, ``L'`` and ``L_D`` enter through
triangular solves.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import lapack

from afvsgp_gym.gp._base import BaseLearner
from afvsgp_gym.gp._linalg import (
    DEFAULT_JITTER,
    check_batch,
    check_count,
    check_matrix,
    check_real,
    check_sample,
    jitter_for,
    jittered_cholesky,
    ubar,
)
from afvsgp_gym.gp._sparse import SELECTION_TOL, fit_collapsed, greedy_inducing
from afvsgp_gym.gp.bound import WhitenedPosterior, _tri
from afvsgp_gym.gp.hyper import DEFAULT_PRIOR, LogNormalPrior, maximise, theta_box
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["SOGP"]


@dataclass(frozen=True)
class _State:
    """Approximate posterior over one inducing set (whitened, see module docstring)."""

    xi: np.ndarray  # [M, b]
    u: np.ndarray  # [M, m]
    ub: np.ndarray  # [M, m+1]
    kbb: np.ndarray  # [M, M] K_bb without jitter
    chol: np.ndarray  # [M, M] L_b = chol(K_bb + eps I)
    eps: float  # absolute jitter in chol
    phi: np.ndarray  # [M, M] Phit_b
    r: np.ndarray  # [M] rt_b
    ld: np.ndarray  # [M, M] L_D = chol(I + Phit_b)
    const: float  # 1/2 log|I + Phit| - 1/2 rt' (I + Phit)^-1 rt (Delta_a part)
    post: WhitenedPosterior | None  # predictions (None for the empty state)
    theta: np.ndarray  # kernel parameters the state was formed with

    @property
    def size(self) -> int:
        return self.xi.shape[0]


def _posterior_terms(chol, phi, r, ld) -> dict:
    """Predictive posterior and the Delta constant from ``(L_b, Phit, rt, L_D)``."""
    post = WhitenedPosterior(chol, phi, r, l_d=ld)
    if not (np.all(np.isfinite(post.w)) and np.all(np.isfinite(post.c))):
        raise np.linalg.LinAlgError("non-finite posterior; check hyperparameters and inputs")
    const = float(np.sum(np.log(np.diag(ld))) - 0.5 * post.c @ post.c)
    return {"phi": phi, "r": r, "ld": ld, "const": const, "post": post}


def _make_state(kernel: ADPKernel, xi, u, ub, kbb, post, eps) -> _State:
    """Complete a state from a step's ``post = (L_b, Phit, rt, L_D)``."""
    return _State(xi=xi, u=u, ub=ub, kbb=kbb, chol=post[0], eps=float(eps),
                  theta=kernel.theta, **_posterior_terms(*post))


def _empty_state(kernel: ADPKernel, b: int, m: int) -> _State:
    z2, z1 = np.zeros((0, 0)), np.zeros(0)
    return _State(np.zeros((0, b)), np.zeros((0, m)), np.zeros((0, m + 1)), z2, z2, 0.0,
                  z2, z1, z2, 0.0, None, kernel.theta)


def _chol(a: np.ndarray, name: str) -> np.ndarray:
    """Lower Cholesky (LAPACK fast path; on failure ``jittered_cholesky``, which warns)."""
    low, info = lapack.dpotrf(a, lower=1, clean=1)
    if info == 0 and np.all(np.isfinite(np.diag(low))):
        return low
    return jittered_cholesky(a, name=name)


def _sandwich(low: np.ndarray, a: np.ndarray, trans: int = 0) -> np.ndarray:
    """``L^-1 a L^-T`` (``trans=0``) or ``L^-T a L^-1`` (``trans=1``) for symmetric ``a``."""
    return _tri(low, _tri(low, a, trans).T, trans)


def _select_pool(kpp: np.ndarray, num: int, tol: float = SELECTION_TOL) -> np.ndarray:
    """The greedy selection of :func:`~afvsgp_gym.gp._sparse.pivoted_cholesky_select` on a small
    explicit candidate gram, by LAPACK's pivoted Cholesky (``dpstrf`` pivots on the largest
    residual diagonal, the same rule, in one call). Returns sorted indices."""
    if kpp.shape[0] == 0:
        return np.zeros(0, dtype=np.intp)
    _, piv, rank, info = lapack.dpstrf(kpp, tol=tol * float(np.max(np.diag(kpp))), lower=1)
    if info < 0:
        raise np.linalg.LinAlgError(f"dpstrf failed (info {info})")
    return np.sort(piv[:min(rank, num)].astype(np.intp) - 1)


class _Step:
    """Matrices of one streaming step (batch f, old state a, new inducing set b)."""

    def __init__(self, kbb, kbf, kffd, kba, kaa, y, s2, prior: _State):
        self.kbb, self.kbf, self.kffd, self.kba, self.kaa = kbb, kbf, kffd, kba, kaa
        self.y, self.s2, self.prior = y, float(s2), prior

    def _data_terms(self, phi, r, a) -> tuple[float, tuple]:
        """Shared tail: factor D = I + Phit; value without the Delta_a terms."""
        y, s2 = self.y, self.s2
        phi = 0.5 * (phi + phi.T)
        ld = _chol(np.eye(phi.shape[0]) + phi, "I + Phi")
        alpha = _tri(ld, r)
        value = (-0.5 * y.shape[0] * np.log(2.0 * np.pi * s2)
                 - 0.5 * (y @ y + self.kffd.sum()) / s2
                 + 0.5 * np.sum(a * a) + 0.5 * alpha @ alpha - np.sum(np.log(np.diag(ld))))
        return float(value), (phi, r, ld)

    def same_set(self):
        """``b = a``, same hyperparameters: ``G = I``, information adds (no projection)."""
        pr = self.prior
        a = _tri(pr.chol, self.kbf) / np.sqrt(self.s2)
        rf = a @ self.y / np.sqrt(self.s2)
        value, post = self._data_terms(pr.phi + a @ a.T, pr.r + rf, a)
        return value + pr.const, (pr.chol, *post)

    def bound(self, grad: bool = False):
        """Collapsed online bound F (module docstring) and, if ``grad``, its adjoints.

        Returns ``(F, (L_b, Phit_b, rt_b, L_D), adj)``; ``adj`` holds dF/dK for
        ``kbb, kbf, kba, kaa, kffd`` (entries treated as independent) and ``log_s2``.
        """
        y, s2, pr = self.y, self.s2, self.prior
        n, ma = y.shape[0], pr.size
        sig = np.sqrt(s2)
        lb = _chol(self.kbb, "K_bb")
        a = _tri(lb, self.kbf) / sig  # [Mb, n]
        rf = a @ y / sig
        phi, r = a @ a.T, rf
        if ma:
            g = _tri(lb, _tri(pr.chol, self.kba.T).T)  # [Mb, Ma] = L_b^-1 K_ba L'^-T
            gp = g @ pr.phi
            phi = phi + gp @ g.T
            r = rf + g @ pr.r
        value, post = self._data_terms(phi, r, a)
        ld = post[2]
        if ma:
            h = (np.eye(ma) if self.kaa is None
                 else _sandwich(pr.chol, self.kaa))  # L'^-1 K_aa L'^-T
            value += pr.const - 0.5 * np.sum(pr.phi * (h - g.T @ g))
        post = (lb, *post)
        if not grad:
            return value, post, None
        d_inv = _tri(ld, _tri(ld, np.eye(ld.shape[0])), 1)  # D^-1 (D >= I: entries <= 1)
        beta = _tri(ld, _tri(ld, r), 1)
        phibar = -0.5 * (np.outer(beta, beta) + d_inv)
        abar_q = 2.0 * phibar @ a + a  # through Phit and |A|^2
        abar = abar_q + np.outer(beta, y) / sig
        d_logs2 = (-0.5 * n + 0.5 * (y @ y + self.kffd.sum()) / s2
                   - 0.5 * np.sum(abar_q * a) - beta @ rf)
        if ma:
            gbar = 2.0 * phibar @ gp + np.outer(beta, pr.r) + gp
            ymat, ybar = np.hstack([a, g]), np.hstack([abar, gbar])
        else:
            ymat, ybar = a, abar
        s = ymat @ ybar.T  # symmetric in exact arithmetic (F is rotation invariant)
        kbb_bar = -0.25 * _sandwich(lb, s + s.T, 1)
        xbar = _tri(lb, ybar, 1)  # L_b^-T Ybar
        adj = {"kbb": kbb_bar, "kbf": xbar[:, :n] / sig, "kffd": np.full(n, -0.5 / s2),
               "log_s2": float(d_logs2)}
        if ma:
            adj["kba"] = _tri(pr.chol, xbar[:, n:].T, 1).T  # Xbar L'^-1
            adj["kaa"] = -0.5 * _sandwich(pr.chol, pr.phi, 1)
        return value, post, adj


class SOGP(BaseLearner):
    """Streaming sparse GP regression (Bui, Nguyen and Turner 2017), collapsed VFE.

    Parameters
    ----------
    kernel : ADPKernel or None
        Initial kernel (cloned, never modified); None: ``ADPKernel.from_data`` in ``fit``.
    noise_variance : float or None
        Initial noise variance; None: ``0.1 var(z)`` in ``fit``.
    num_inducing : int
        Maximum number M of inducing points.
    batch_size : int
        ``update`` buffers samples and runs one streaming step when this many are buffered.
        Buffered samples do not affect predictions until then (``flush`` forces a step).
        Default 1 (a step per sample, as the filter runs its learners; docs/learners.md).
    optimise_online : bool
        Re-optimise kernel and noise on Bui's online bound at every step (L-BFGS-B,
        ``online_maxiter`` iterations, analytic gradients; inducing set chosen first). Off by
        default: hyperparameters from ``fit`` stay frozen, as for the other learners.
    online_maxiter : int
        Iterations of the per-step optimisation.
    inducing : tuple (xi_o (M, b), u_o (M, m)) or None
        Initial inducing set; None: chosen from the first batch.
    adapt_inducing : bool
        If True, each step chooses the new set ``b`` from the old points and the batch by
        greedy pivoted Cholesky (largest conditional prior variance first, at most M,
        near-duplicates excluded). If False the set stays fixed after the first step.
    jitter : float
        Relative jitter on K_bb (:func:`~afvsgp_gym.gp._linalg.jitter_for`).
    fit_maxiter : int
        L-BFGS-B iterations per hyperparameter fit in ``fit``.
    prior : LogNormalPrior or None
        Weak prior on the log kernel parameters in ``fit``, centred at the initial kernel
        (:mod:`afvsgp_gym.gp.hyper`); None maximises the bound alone. The per-step
        ``optimise_online`` search has no prior (a box of +-8 around the current values).

    Attributes
    ----------
    kernel_ : ADPKernel
    noise_variance_ : float
    inducing_xi_ : ndarray of shape (M, b)
    inducing_u_ : ndarray of shape (M, m)
    q_mean_, q_cov_ : ndarray of shape (M,), (M, M)
        ``q(b) = N(q_mean_, q_cov_)`` over the inducing outputs.
    bound_ : float
        Sum of the per-step bounds (an approximation of ``log p(all z)``); after ``fit`` the
        Titsias bound (eq. 18) of the fit data at the fitted hyperparameters on the final
        inducing set.
    n_seen_ : int
        Samples absorbed into the posterior (buffered ones excluded).
    jitter_ : float
        Absolute jitter on the current inducing set's K_bb.

    Cost per step with M inducing points, n batch samples, b features, m actions:
    O(n (M+n) (m+1) b) for the kernel (the old block K_aa is reused while the hyperparameters
    are unchanged) and O(M^2 (M+n)) for the algebra, independent of the stream length
    (measured figures: ``afvsgp-gym bench --only gp``, docs/performance.md).
    """

    def __init__(self, kernel: ADPKernel | None = None, noise_variance: float | None = None,
                 num_inducing: int = 20, batch_size: int = 1, *,
                 optimise_online: bool = False, online_maxiter: int = 20,
                 inducing=None, adapt_inducing: bool = True, jitter: float = DEFAULT_JITTER,
                 fit_maxiter: int = 200, prior: LogNormalPrior | None = DEFAULT_PRIOR):
        self.kernel = kernel
        self.noise_variance = noise_variance
        self.num_inducing = num_inducing
        self.batch_size = batch_size
        self.optimise_online = optimise_online
        self.online_maxiter = online_maxiter
        self.inducing = inducing
        self.adapt_inducing = adapt_inducing
        self.jitter = jitter
        self.fit_maxiter = fit_maxiter
        self.prior = prior
        self._buffer: list[tuple[np.ndarray, np.ndarray, float]] = []

    # ----------------------------------------------------------------- checks
    def _check_params(self) -> None:
        super()._check_params()
        for name in ("num_inducing", "batch_size", "online_maxiter", "fit_maxiter"):
            check_count(getattr(self, name), name)
        check_real(self.jitter, "jitter", low=0.0)

    def _check_inducing(self, b: int, m: int):
        if self.inducing is None:
            return None
        try:
            xi_o, u_o = self.inducing
        except (TypeError, ValueError):
            raise ValueError("inducing must be a pair (xi_o, u_o)") from None
        xi_o = check_matrix(xi_o, "inducing", ncols=b)
        u_o = check_matrix(u_o, "inducing", ncols=m, nrows=xi_o.shape[0])
        if xi_o.shape[0] == 0:
            raise ValueError("inducing must contain at least one point")
        return xi_o, u_o

    def _sample_dims(self) -> tuple[int, int] | None:
        """(b, m) fixed by the fitted or given kernel or the buffer; None if still free."""
        if self._fitted():
            return self.kernel_.input_dim, self.kernel_.action_dim
        if self.kernel is not None:
            return self.kernel.input_dim, self.kernel.action_dim
        if self._buffer:
            return self._buffer[0][0].shape[0], self._buffer[0][1].shape[0]
        return None

    def _fitted(self) -> bool:
        return hasattr(self, "_state")

    def _check_fitted(self) -> None:
        if not self._fitted():
            raise RuntimeError("SOGP is not fitted: call fit first, or give kernel and "
                               "noise_variance and update until a batch is full")

    # ----------------------------------------------------------------- fit
    def fit(self, xi, u, z, learn_hyperparameters: bool = True) -> SOGP:
        """Initial batch: Titsias posterior (eqs. 17-18), hyperparameters by the bound plus the
        prior (:func:`~afvsgp_gym.gp._sparse.fit_collapsed`).

        Inducing points: ``inducing`` if given, else up to M points of the data by pivoted
        Cholesky under the fitted kernel. Resets the stream and the buffer.
        """
        self._check_params()
        dims = {} if self.kernel is None else {"input_dim": self.kernel.input_dim,
                                               "action_dim": self.kernel.action_dim}
        xi, u, z = check_batch(xi, u, z, **dims)
        b, m = xi.shape[1], u.shape[1]
        fixed = self._check_inducing(b, m)
        kernel, s2 = self._init_hyper(xi, u, z)
        if fixed is not None:
            def select(_kernel):
                return fixed
        else:
            def select(k):
                idx = np.sort(greedy_inducing(k, xi, u, self.num_inducing))
                return xi[idx], u[idx]
        if learn_hyperparameters:
            kernel, s2, (xi_o, u_o) = fit_collapsed(
                kernel, s2, xi, u, z, np.ones(xi.shape[0]), select, jitter=self.jitter,
                maxiter=self.fit_maxiter, prior=self.prior)
        else:
            xi_o, u_o = select(kernel)
        ub, ub_o = ubar(u), ubar(u_o)
        kbb = kernel._gram(xi_o, ub_o)
        eps = jitter_for(kbb, self.jitter)
        step = _Step(kbb + eps * np.eye(kbb.shape[0]), kernel._gram(xi_o, ub_o, xi, ub),
                     kernel._diag(ub), None, None, z, s2, _empty_state(kernel, b, m))
        value, post, _ = step.bound()
        state = _make_state(kernel, xi_o, u_o, ub_o, kbb, post, eps)
        # commit (nothing above touched self)
        self.kernel_, self.noise_variance_ = kernel, s2
        self._set_state(state)
        self.bound_ = value
        self.n_seen_ = xi.shape[0]
        self.n_steps_ = 1
        self._buffer = []
        return self

    # ----------------------------------------------------------------- streaming
    def update(self, xi, u, z) -> SOGP:
        """Buffer one sample; run a streaming step when ``batch_size`` samples are buffered.

        Before ``fit``: a full buffer starts the stream from the prior if ``kernel`` and
        ``noise_variance`` were given, else it is passed to ``fit``.
        """
        dims = self._sample_dims()
        if dims is None:
            xi = check_matrix(xi, "xi", ndim=1)
            u = check_matrix(u, "u", ndim=1)
            z = float(check_matrix(z, "z", ndim=0))
        else:
            xi, u, z = check_sample(xi, u, z, input_dim=dims[0], action_dim=dims[1])
        self._buffer.append((xi, u, z))
        if len(self._buffer) >= self.batch_size:
            try:
                self.flush()
            except Exception:
                self._buffer.pop()  # leave the learner exactly as before this call
                raise
        return self

    def flush(self) -> SOGP:
        """Absorb the buffered samples now (one streaming step); no-op if the buffer is empty.

        On failure the buffer and the posterior are left as they were.
        """
        if not self._buffer:
            return self
        xi = np.array([s[0] for s in self._buffer])
        u = np.array([s[1] for s in self._buffer])
        z = np.array([s[2] for s in self._buffer])
        if not self._fitted():
            if self.kernel is None or self.noise_variance is None:
                return self.fit(xi, u, z)
            self._check_params()
            kernel, s2 = self.kernel.clone(), float(self.noise_variance)
            prior = _empty_state(kernel, xi.shape[1], u.shape[1])
            fixed = self._check_inducing(xi.shape[1], u.shape[1])
            value, state, kernel, s2 = self._stream_step(prior, xi, u, z, fixed, kernel, s2)
            self.bound_, self.n_seen_, self.n_steps_ = 0.0, 0, 0
        else:
            value, state, kernel, s2 = self._stream_step(self._state, xi, u, z, None,
                                                         self.kernel_, self.noise_variance_)
        self.kernel_, self.noise_variance_ = kernel, s2
        self._set_state(state)
        self.bound_ += value
        self.n_seen_ += xi.shape[0]
        self.n_steps_ += 1
        self._buffer = []
        return self

    def _stream_step(self, prior: _State, xi, u, z, fixed, kernel: ADPKernel, s2: float):
        """One Bui step from ``prior`` on batch (xi, u, z); returns new (F, state, kernel, s2).

        ``fixed``: inducing set for a step from the empty prior (else chosen or kept).
        """
        ma = prior.size
        if fixed is not None:
            xi_p, u_p = np.vstack([fixed[0], xi]), np.vstack([fixed[1], u])
            n_old = fixed[0].shape[0]
        else:
            xi_p, u_p = np.vstack([prior.xi, xi]), np.vstack([prior.u, u])
            n_old = ma
        ub_p = ubar(u_p)
        if ma and np.array_equal(prior.theta, kernel.theta):
            # pooled gram (old first, then f); the old block is known from the state
            kfp = kernel._gram(xi, ub_p[ma:], xi_p, ub_p)  # [n, Ma+n]
            kpp = np.empty((xi_p.shape[0], xi_p.shape[0]))
            kpp[:ma, :ma] = prior.kbb
            kpp[ma:] = kfp
            kpp[:ma, ma:] = kfp[:, :ma].T
            kpp[ma:, ma:] = 0.5 * (kfp[:, ma:] + kfp[:, ma:].T)
        else:
            kpp = kernel._gram(xi_p, ub_p)
        if fixed is not None or (ma and not self.adapt_inducing):
            idx = np.arange(n_old)
        else:
            idx = _select_pool(kpp, self.num_inducing)
        if self.optimise_online:
            kernel_new, s2 = self._online_hyper(prior, xi_p, u_p, idx, n_old, z, kernel, s2)
            if kernel_new is not kernel:
                kernel = kernel_new
                kpp = kernel._gram(xi_p, ub_p)
        if (ma and idx.shape[0] == ma and idx[-1] == ma - 1  # sorted, unique: idx = 0..Ma-1
                and np.array_equal(prior.theta, kernel.theta)):
            # b = a (then eps_b = eps_a too): information adds, only Phit and rt change
            step = _Step(None, kpp[:ma, ma:], np.diag(kpp)[ma:], None, None, z, s2, prior)
            value, post = step.same_set()
            return value, replace(prior, **_posterior_terms(*post)), kernel, s2
        step, eps = self._build_step(kernel, s2, prior, kpp, idx, n_old, z)
        value, post, _ = step.bound()
        state = _make_state(kernel, xi_p[idx], u_p[idx], ub_p[idx], kpp[np.ix_(idx, idx)], post,
                            eps)
        return value, state, kernel, s2

    def _build_step(self, kernel, s2, prior: _State, kpp, idx, n_old, z):
        """Slice the step's matrices from the pooled gram ``kpp`` (old/fixed first, then f)."""
        ma = prior.size
        f = np.arange(n_old, kpp.shape[0])
        kbb = kpp[np.ix_(idx, idx)]
        eps = jitter_for(kbb, self.jitter)
        kbb[np.diag_indices_from(kbb)] += eps
        kba = kaa = None
        if ma:
            kba = kpp[np.ix_(idx, np.arange(ma))]
            old = np.nonzero(idx < ma)[0]
            kba[old, idx[old]] += np.sqrt(eps * prior.eps)  # shared jitter, same input
            if not np.array_equal(prior.theta, kernel.theta):
                kaa = kpp[:ma, :ma].copy()
                kaa[np.diag_indices_from(kaa)] += prior.eps
        step = _Step(kbb, kpp[np.ix_(idx, f)], np.diag(kpp)[f], kba, kaa, z, s2, prior)
        return step, eps

    def _online_hyper(self, prior, xi_p, u_p, idx, n_old, z, kernel, s2):
        """Maximise Bui's online bound over (theta, log s2) with the inducing set fixed, in a
        box of +-8 around the current values."""
        ub_p = ubar(u_p)
        work = kernel.clone()
        eps_fixed = jitter_for(kernel._gram(xi_p[idx], ub_p[idx]), self.jitter)
        ma = prior.size
        f = np.arange(n_old, xi_p.shape[0])

        def evidence(p):
            work.theta = p[:-1]
            return _online_bound_and_grad(work, float(np.exp(p[-1])), prior, xi_p, ub_p, idx,
                                          f, ma, z, eps_fixed)

        p0 = np.concatenate([kernel.theta, [np.log(s2)]])
        p, _ = maximise(evidence, p0, theta_box(p0), self.online_maxiter)
        if np.array_equal(p, p0):
            return kernel, s2
        return kernel.with_theta(p[:-1]), float(np.exp(p[-1]))

    # ----------------------------------------------------------------- state
    def _set_state(self, state: _State) -> None:
        self._state = state
        self.inducing_xi_ = state.xi.copy()
        self.inducing_u_ = state.u.copy()

    @property
    def q_mean_(self) -> np.ndarray:
        """Mean of q(b): ``L_b D^-1 rt``."""
        self._check_fitted()
        st = self._state
        return st.chol @ _tri(st.ld, _tri(st.ld, st.r), 1)

    @property
    def q_cov_(self) -> np.ndarray:
        """Covariance of q(b): ``L_b D^-1 L_b'``."""
        self._check_fitted()
        st = self._state
        x = _tri(st.ld, st.chol.T)  # L_D^-1 L_b'
        return x.T @ x

    @property
    def jitter_(self) -> float:
        """Absolute jitter on the current K_bb (:func:`~afvsgp_gym.gp._linalg.jitter_for`)."""
        self._check_fitted()
        return self._state.eps

    @property
    def n_buffered(self) -> int:
        """Samples waiting for the next streaming step."""
        return len(self._buffer)

    # ----------------------------------------------------------------- prediction
    def _predict(self, xi, u):
        """Mean and variance of the latent f at (xi (N, b), u (N, m)) (eq. 14)."""
        st = self._state
        ub = ubar(u)
        kdiag = self.kernel_._diag(ub)
        if st.size == 0:
            return np.zeros(xi.shape[0]), kdiag
        return st.post.predict(self.kernel_._gram(xi, ub, st.xi, st.ub), kdiag)

    def _predict_affine(self, xi):
        """Affine form (eqs. 20-21); Sigma is made PSD (a round-off negative eigenvalue is
        lifted to zero by a tiny diagonal shift)."""
        st = self._state
        var = self.kernel_._var
        if st.size == 0:
            n, c = xi.shape[0], var.shape[0]
            sigma = np.zeros((n, c, c))
            sigma[:, np.arange(c), np.arange(c)] = var
            return np.zeros((n, c)), sigma
        coef, sigma = st.post.affine(self.kernel_._cross_affine(xi, st.xi, st.ub), var)
        return coef, _clip_psd(sigma)


def _online_bound_and_grad(kernel, s2, prior, xi_p, ub_p, idx, f, ma, z, eps):
    """Bui's online bound and its gradient w.r.t. ``concat(theta, [log s2])``.

    Pool ``p`` = old points (first ``ma``) then the batch ``f``; ``b = p[idx]``; ``eps`` fixed.
    """
    kpp = kernel._gram(xi_p, ub_p)
    kbb = kpp[np.ix_(idx, idx)]
    kbb[np.diag_indices_from(kbb)] += eps
    kba = kaa = None
    if ma:
        kba = kpp[np.ix_(idx, np.arange(ma))]
        old = np.nonzero(idx < ma)[0]
        kba[old, idx[old]] += np.sqrt(eps * prior.eps)
        kaa = kpp[:ma, :ma].copy()
        kaa[np.diag_indices_from(kaa)] += prior.eps
    step = _Step(kbb, kpp[np.ix_(idx, f)], np.diag(kpp)[f], kba, kaa, z, s2, prior)
    value, _, adj = step.bound(grad=True)
    g = np.zeros_like(kpp)  # dF/dK_pp (jitter constant)
    g[np.ix_(idx, idx)] += adj["kbb"]
    g[np.ix_(idx, f)] += adj["kbf"]
    if ma:
        a = np.arange(ma)
        g[np.ix_(idx, a)] += adj["kba"]
        g[np.ix_(a, a)] += adj["kaa"]
    grad = kernel.grad_contract(g, xi_p, ub_p) + kernel.grad_diag_contract(adj["kffd"], ub_p[f])
    return value, np.concatenate([grad, [adj["log_s2"]]])


def _clip_psd(sigma: np.ndarray) -> np.ndarray:
    """Make a stack of symmetric matrices PSD: if round-off left a negative eigenvalue
    ``lam``, add ``|lam|`` (plus 1e-14 of the largest diagonal entry) to the diagonal, a
    slight, conservative variance inflation (cheaper than re-assembling an eigen-decomposition)."""
    lam = np.linalg.eigvalsh(sigma)[:, 0]
    bad = lam < 0.0
    if np.any(bad):
        c = sigma.shape[1]
        top = np.max(np.diagonal(sigma, axis1=1, axis2=2), axis=1)
        shift = np.where(bad, -lam + 1e-14 * np.abs(top), 0.0)
        sigma[:, np.arange(c), np.arange(c)] += shift[:, None]
    return sigma
