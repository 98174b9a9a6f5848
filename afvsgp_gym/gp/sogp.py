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

Jitter: the inducing variables are ``f(b) + e`` with ``var(e) = eps_b = jitter * mean diag
K_bb`` (relative jitter, ``DEFAULT_JITTER``); an old and a new inducing variable at the same
input share their jitter (covariance ``sqrt(eps_a eps_b)``), which keeps ``b = a`` exact.

Predictions (paper eqs. 14, 20-21): ``mean = K_*b w``, ``w = K_bb^-1 m_b``;
``var = k_** - K_*b (K_bb^-1 - K_bb^-1 S_b K_bb^-1) K_b*``; per component for ``predict_affine``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import lapack
from scipy.optimize import minimize

from afvsgp_gym.gp._linalg import (
    DEFAULT_JITTER,
    check_batch,
    check_matrix,
    check_sample,
    jittered_cholesky,
    ubar,
)
from afvsgp_gym.gp.bound import weighted_bound_and_grad
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["SOGP"]

#: Candidates whose conditional prior variance is below this fraction of the largest diagonal
#: are never chosen as inducing points (guards against near-duplicate inducing inputs).
SELECTION_TOL = 1e-6


@dataclass(frozen=True)
class _State:
    """Approximate posterior over one inducing set (whitened, see module docstring)."""

    xi: np.ndarray  # [M, b]
    u: np.ndarray  # [M, m]
    ub: np.ndarray  # [M, m+1]
    kbb: np.ndarray  # [M, M] K_bb without jitter
    chol: np.ndarray  # [M, M] L_b = chol(K_bb + eps I)
    chol_inv: np.ndarray  # [M, M] L_b^-1
    eps: float  # absolute jitter in chol
    phi: np.ndarray  # [M, M] Phit_b
    r: np.ndarray  # [M] rt_b
    d_inv: np.ndarray  # [M, M] (I + Phit_b)^-1
    const: float  # 1/2 log|I + Phit| - 1/2 rt' (I + Phit)^-1 rt (Delta_a part)
    w: np.ndarray  # [M] K_bb^-1 m_b (mean weights)
    q: np.ndarray  # [M, M] K_bb^-1 - K_bb^-1 S_b K_bb^-1
    theta: np.ndarray  # kernel parameters the state was formed with
    inv_ls: np.ndarray  # [m+1, b] prediction caches: 1 / lengthscales,
    var: np.ndarray  # [m+1] component variances,
    xs: np.ndarray  # [m+1, M, b] scaled inducing inputs,
    ns: np.ndarray  # [m+1, M] and their squared norms

    @property
    def size(self) -> int:
        return self.xi.shape[0]


def _posterior_terms(chol_inv, phi, r, ld, ld_inv) -> dict:
    """Predictive caches and the Delta constant from (L_b^-1, Phit, rt, L_D, L_D^-1)."""
    m = phi.shape[0]
    d_inv = ld_inv.T @ ld_inv
    alpha = ld_inv @ r
    w = chol_inv.T @ (d_inv @ r)
    q = chol_inv.T @ (np.eye(m) - d_inv) @ chol_inv
    q = 0.5 * (q + q.T)
    if not (np.all(np.isfinite(w)) and np.all(np.isfinite(q))):
        raise np.linalg.LinAlgError("non-finite posterior; check hyperparameters and inputs")
    const = float(np.sum(np.log(np.diag(ld))) - 0.5 * alpha @ alpha)
    return {"phi": phi, "r": r, "d_inv": d_inv, "const": const, "w": w, "q": q}


def _make_state(kernel: ADPKernel, xi, u, ub, kbb, post, eps) -> _State:
    """Complete a state from a step's ``post = (L_b, L_b^-1, Phit, rt, L_D, L_D^-1)``."""
    chol, chol_inv = post[:2]
    terms = _posterior_terms(*post[1:])
    inv_ls = 1.0 / kernel.lengthscales
    xs = xi[None, :, :] * inv_ls[:, None, :]
    return _State(xi=xi, u=u, ub=ub, kbb=kbb, chol=chol, chol_inv=chol_inv, eps=float(eps),
                  theta=kernel.theta, inv_ls=inv_ls, var=kernel.variances, xs=xs,
                  ns=np.einsum("imb,imb->im", xs, xs), **terms)


def _empty_state(kernel: ADPKernel, b: int, m: int) -> _State:
    z2, z1 = np.zeros((0, 0)), np.zeros(0)
    c = kernel.n_components
    return _State(np.zeros((0, b)), np.zeros((0, m)), np.zeros((0, m + 1)), z2, z2, z2, 0.0,
                  z2, z1, z2, 0.0, z1, z2, kernel.theta, 1.0 / kernel.lengthscales,
                  kernel.variances, np.zeros((c, 0, b)), np.zeros((c, 0)))


def _chol(a: np.ndarray, name: str) -> np.ndarray:
    """Lower Cholesky (LAPACK fast path; on failure ``jittered_cholesky``, which warns)."""
    low, info = lapack.dpotrf(a, lower=1, clean=1)
    if info == 0 and np.all(np.isfinite(np.diag(low))):
        return low
    return jittered_cholesky(a, name=name)


def _tri_inv(low: np.ndarray) -> np.ndarray:
    """Inverse of a lower-triangular factor."""
    if low.shape[0] == 0:
        return low.copy()
    inv, info = lapack.dtrtri(low, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError("singular triangular factor")
    return inv


def _gram(kernel: ADPKernel, xi1, ub1, xi2=None, ub2=None) -> np.ndarray:
    """ADP gram (eq. 19) from the kernel's RBF components; ``ub`` = ubar rows."""
    comp = kernel._components(xi1, xi2)  # [m+1, N1, N2]
    if xi2 is None:
        gram = np.einsum("inj,ni,ji->nj", comp, ub1, ub1)
        return 0.5 * (gram + gram.T)
    return np.einsum("inj,ni,ji->nj", comp, ub1, ub2)


def _select(diag: np.ndarray, column, num: int, tol: float = SELECTION_TOL) -> np.ndarray:
    """Greedy pivoted Cholesky: up to ``num`` candidates of largest conditional variance.

    ``column(j)`` returns the candidates' covariance with candidate ``j``. Greedily minimises
    ``tr(K_cc - Q_cc)`` over the candidates (the trace term of the collapsed bound). Returns
    sorted indices; stops early when every remaining candidate is (nearly) explained.
    """
    c = diag.shape[0]
    k_max = min(num, c)
    d = diag.astype(np.float64, copy=True)
    floor = tol * float(d.max()) if c else 0.0
    lcols = np.zeros((k_max, c))
    chosen = np.empty(k_max, dtype=np.intp)
    k = 0
    while k < k_max:
        j = int(d.argmax())
        dj = d[j]
        if not dj > floor:
            break
        col = column(j) - lcols[:k, j] @ lcols[:k]
        col *= 1.0 / np.sqrt(dj)
        lcols[k] = col
        d -= col * col
        d[j] = -np.inf
        chosen[k] = j
        k += 1
    return np.sort(chosen[:k])


def _select_pool(kpp: np.ndarray, num: int, tol: float = SELECTION_TOL) -> np.ndarray:
    """``_select`` on a small explicit candidate gram via LAPACK pivoted Cholesky (dpstrf).

    dpstrf pivots on the largest residual diagonal, i.e. the same greedy rule, in one call.
    """
    if kpp.shape[0] == 0:
        return np.zeros(0, dtype=np.intp)
    _, piv, rank, info = lapack.dpstrf(kpp, tol=tol * float(np.max(np.diag(kpp))), lower=1)
    if info < 0:
        return _select(np.diag(kpp), lambda j: kpp[:, j], num, tol)
    return np.sort(piv[:min(rank, num)].astype(np.intp) - 1)


class _Step:
    """Matrices of one streaming step (batch f, old state a, new inducing set b)."""

    def __init__(self, kbb, kbf, kffd, kba, kaa, y, s2, prior: _State):
        self.kbb, self.kbf, self.kffd, self.kba, self.kaa = kbb, kbf, kffd, kba, kaa
        self.y, self.s2, self.prior = y, float(s2), prior

    def _data_terms(self, phi, r, a) -> tuple[float, tuple, np.ndarray]:
        """Shared tail: factor D = I + Phit; value without the Delta_a terms."""
        y, s2 = self.y, self.s2
        phi = 0.5 * (phi + phi.T)
        ld = _chol(np.eye(phi.shape[0]) + phi, "I + Phi")
        ld_inv = _tri_inv(ld)
        alpha = ld_inv @ r
        value = (-0.5 * y.shape[0] * np.log(2.0 * np.pi * s2)
                 - 0.5 * (y @ y + self.kffd.sum()) / s2
                 + 0.5 * np.sum(a * a) + 0.5 * alpha @ alpha - np.sum(np.log(np.diag(ld))))
        return float(value), (phi, r, ld, ld_inv), ld_inv

    def same_set(self):
        """``b = a``, same hyperparameters: ``G = I``, information adds (no projection)."""
        pr = self.prior
        a = pr.chol_inv @ self.kbf / np.sqrt(self.s2)
        rf = a @ self.y / np.sqrt(self.s2)
        value, post, _ = self._data_terms(pr.phi + a @ a.T, pr.r + rf, a)
        return value + pr.const, (pr.chol, pr.chol_inv, *post)

    def bound(self, grad: bool = False):
        """Collapsed online bound F (module docstring) and, if ``grad``, its adjoints.

        Returns ``(F, (L_b, L_b^-1, Phit_b, rt_b, L_D, L_D^-1), adj)``; ``adj`` holds dF/dK
        for ``kbb, kbf, kba, kaa, kffd`` (entries treated as independent) and ``log_s2``.
        """
        y, s2, pr = self.y, self.s2, self.prior
        n, ma = y.shape[0], pr.size
        sig = np.sqrt(s2)
        lb = _chol(self.kbb, "K_bb")
        li = _tri_inv(lb)
        a = li @ self.kbf / sig  # [Mb, n]
        rf = a @ y / sig
        phi, r = a @ a.T, rf
        if ma:
            g = li @ self.kba @ pr.chol_inv.T  # [Mb, Ma] = L_b^-1 K_ba L'^-T
            gp = g @ pr.phi
            phi = phi + gp @ g.T
            r = rf + g @ pr.r
        value, post, ld_inv = self._data_terms(phi, r, a)
        if ma:
            h = (np.eye(ma) if self.kaa is None
                 else pr.chol_inv @ self.kaa @ pr.chol_inv.T)  # L'^-1 K_aa L'^-T
            value += pr.const - 0.5 * np.sum(pr.phi * (h - g.T @ g))
        post = (lb, li, *post)
        if not grad:
            return value, post, None
        d_inv = ld_inv.T @ ld_inv
        beta = d_inv @ r
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
        kbb_bar = -0.25 * li.T @ (s + s.T) @ li
        xbar = li.T @ ybar
        adj = {"kbb": kbb_bar, "kbf": xbar[:, :n] / sig, "kffd": np.full(n, -0.5 / s2),
               "log_s2": float(d_logs2)}
        if ma:
            adj["kba"] = xbar[:, n:] @ pr.chol_inv
            adj["kaa"] = -0.5 * pr.chol_inv.T @ pr.phi @ pr.chol_inv
        return value, post, adj


class SOGP:
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
        Default 1 (a step per sample): in the filter loop the lag of larger batches costs
        accuracy (point-mass env, one-step error of Delta B about 10x larger with 10).
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
        Relative jitter: ``jitter * mean diag K_bb`` is added to K_bb.
    fit_maxiter : int
        L-BFGS-B iterations of the hyperparameter fit in ``fit``.

    Attributes
    ----------
    kernel_ : ADPKernel
    noise_variance_ : float
    inducing_xi_ : ndarray of shape (M, b)
    inducing_u_ : ndarray of shape (M, m)
    q_mean_, q_cov_ : ndarray of shape (M,), (M, M)
        ``q(b) = N(q_mean_, q_cov_)`` over the inducing outputs.
    bound_ : float
        Sum of the per-step bounds (an approximation of ``log p(all z)``).
    n_seen_ : int
        Samples absorbed into the posterior (buffered ones excluded).

    Cost per step with M inducing points, n batch samples, b features, m actions:
    O(n (M+n) (m+1) b) for the kernel (the old block K_aa is reused while the hyperparameters
    are unchanged) and O(M^2 (M+n)) for the algebra, independent of the stream length. At
    M=20, b=20, m=7, one BLAS thread, on a loaded 2-core machine (see the GP benchmark):
    ~0.3 ms per step with n=1 (most steps keep the inducing set: no projection), 0.5-0.6 ms
    with n=10..20, ~20 us for an update that only buffers, ~80 us per ``predict_affine``.
    ``optimise_online`` adds about 60 ms per step.
    """

    def __init__(self, kernel: ADPKernel | None = None, noise_variance: float | None = None,
                 num_inducing: int = 20, batch_size: int = 1, *,
                 optimise_online: bool = False, online_maxiter: int = 20,
                 inducing=None, adapt_inducing: bool = True, jitter: float = DEFAULT_JITTER,
                 fit_maxiter: int = 200):
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
        self._buffer: list[tuple[np.ndarray, np.ndarray, float]] = []

    # ----------------------------------------------------------------- checks
    def _check_params(self) -> None:
        if self.kernel is not None and not isinstance(self.kernel, ADPKernel):
            raise ValueError(f"kernel must be an ADPKernel or None, got {type(self.kernel)}")
        if self.noise_variance is not None and not (
                np.isfinite(self.noise_variance) and self.noise_variance > 0):
            raise ValueError(f"noise_variance must be positive, got {self.noise_variance}")
        for name in ("num_inducing", "batch_size", "online_maxiter", "fit_maxiter"):
            val = getattr(self, name)
            if not (isinstance(val, int | np.integer) and val >= 1):
                raise ValueError(f"{name} must be a positive integer, got {val!r}")
        if not (np.isfinite(self.jitter) and self.jitter >= 0):
            raise ValueError(f"jitter must be non-negative, got {self.jitter}")

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

    def _dims(self) -> tuple[int, int] | None:
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

    def _require_fitted(self) -> None:
        if not self._fitted():
            raise RuntimeError("SOGP is not fitted: call fit first, or give kernel and "
                               "noise_variance and update until a batch is full")

    # ----------------------------------------------------------------- fit
    def fit(self, xi, u, z, learn_hyperparameters: bool = True) -> SOGP:
        """Initial batch: Titsias posterior (eqs. 17-18), hyperparameters by the bound.

        Inducing points: ``inducing`` if given, else up to M points of the data by pivoted
        Cholesky (re-chosen after the hyperparameter fit). Resets the stream and the buffer.
        """
        self._check_params()
        dims = {} if self.kernel is None else {"input_dim": self.kernel.input_dim,
                                               "action_dim": self.kernel.action_dim}
        xi, u, z = check_batch(xi, u, z, **dims)
        b, m = xi.shape[1], u.shape[1]
        fixed = self._check_inducing(b, m)
        kernel = self.kernel.clone() if self.kernel is not None else ADPKernel.from_data(xi, u, z)
        s2 = float(self.noise_variance) if self.noise_variance is not None else _noise_init(z)
        ub = ubar(u)
        if learn_hyperparameters:
            xi_o, u_o = fixed if fixed is not None else self._select_data(kernel, xi, ub, u)
            kernel, s2 = self._fit_hyper(kernel, s2, xi, u, z, xi_o, u_o)
        if fixed is not None:
            xi_o, u_o = fixed
        else:
            xi_o, u_o = self._select_data(kernel, xi, ub, u)
        ub_o = ubar(u_o)
        kbb = _gram(kernel, xi_o, ub_o)
        eps = self._eps(kbb)
        step = _Step(kbb + eps * np.eye(kbb.shape[0]), _gram(kernel, xi_o, ub_o, xi, ub),
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

    def _eps(self, kbb_raw: np.ndarray) -> float:
        return float(self.jitter * np.mean(np.diag(kbb_raw))) if kbb_raw.size else 0.0

    def _select_data(self, kernel, xi, ub, u):
        """Inducing points chosen from a (possibly large) data set, columns on demand."""
        idx = _select(kernel._diag(ub),
                      lambda j: _gram(kernel, xi, ub, xi[j:j + 1], ub[j:j + 1])[:, 0],
                      self.num_inducing)
        return xi[idx], u[idx]

    def _fit_hyper(self, kernel, s2, xi, u, z, xi_o, u_o):
        """Maximise the Titsias bound (bound.py, unit weights) with L-BFGS-B."""
        ub_o = ubar(u_o)
        eps = self._eps(_gram(kernel, xi_o, ub_o))
        weights = np.ones(xi.shape[0])
        work = kernel.clone()

        def objective(p):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                try:
                    val, grad = weighted_bound_and_grad(p, work, xi, u, z, weights, xi_o, u_o,
                                                        eps)
                except np.linalg.LinAlgError:
                    return 1e25, np.zeros_like(p)
            if not np.isfinite(val) or not np.all(np.isfinite(grad)):
                return 1e25, np.zeros_like(p)
            return -val, -grad

        p0 = np.concatenate([kernel.theta, [np.log(s2)]])
        p = self._optimise(objective, p0, self.fit_maxiter, zscale=_scale(z))
        return kernel.with_theta(p[:-1]), float(np.exp(p[-1]))

    @staticmethod
    def _optimise(objective, p0, maxiter, zscale=None):
        """L-BFGS-B within log p0 +- 7; returns p0 if nothing better is found.

        ``zscale``: bound the noise variance to [1e-6, 10] * zscale instead (and start inside).
        """
        lo = p0 - 7.0
        hi = p0 + 7.0
        if zscale is not None:
            lo[-1] = np.log(1e-6 * zscale)
            hi[-1] = np.log(10.0 * zscale)
            p0 = np.clip(p0, lo, hi)
        f0 = objective(p0)[0]
        res = minimize(objective, p0, jac=True, method="L-BFGS-B",
                       bounds=list(zip(lo, hi, strict=True)), options={"maxiter": maxiter})
        return res.x if np.isfinite(res.fun) and res.fun <= f0 else p0

    # ----------------------------------------------------------------- streaming
    def update(self, xi, u, z) -> SOGP:
        """Buffer one sample; run a streaming step when ``batch_size`` samples are buffered.

        Before ``fit``: a full buffer starts the stream from the prior if ``kernel`` and
        ``noise_variance`` were given, else it is passed to ``fit``.
        """
        dims = self._dims()
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
            kfp = _gram(kernel, xi, ub_p[ma:], xi_p, ub_p)  # [n, Ma+n]
            kpp = np.empty((xi_p.shape[0], xi_p.shape[0]))
            kpp[:ma, :ma] = prior.kbb
            kpp[ma:] = kfp
            kpp[:ma, ma:] = kfp[:, :ma].T
            kpp[ma:, ma:] = 0.5 * (kfp[:, ma:] + kfp[:, ma:].T)
        else:
            kpp = _gram(kernel, xi_p, ub_p)
        if fixed is not None or (ma and not self.adapt_inducing):
            idx = np.arange(n_old)
        else:
            idx = _select_pool(kpp, self.num_inducing)
        if self.optimise_online:
            kernel_new, s2 = self._online_hyper(prior, xi_p, u_p, idx, n_old, z, kernel, s2)
            if kernel_new is not kernel:
                kernel = kernel_new
                kpp = _gram(kernel, xi_p, ub_p)
        if (ma and idx.shape[0] == ma and idx[-1] == ma - 1  # sorted, unique: idx = 0..Ma-1
                and np.array_equal(prior.theta, kernel.theta)):
            # b = a (then eps_b = eps_a too): information adds, only Phit and rt change
            step = _Step(None, kpp[:ma, ma:], np.diag(kpp)[ma:], None, None, z, s2, prior)
            value, post = step.same_set()
            return value, replace(prior, **_posterior_terms(*post[1:])), kernel, s2
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
        eps = self._eps(kbb)
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
        """Maximise Bui's online bound over (theta, log s2) with the inducing set fixed."""
        ub_p = ubar(u_p)
        work = kernel.clone()
        eps_fixed = self._eps(_gram(kernel, xi_p[idx], ub_p[idx]))
        ma = prior.size
        f = np.arange(n_old, xi_p.shape[0])

        def objective(p):
            work.theta = p[:-1]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                try:
                    val, grad = _online_bound_and_grad(work, float(np.exp(p[-1])), prior, xi_p,
                                                       ub_p, idx, f, ma, z, eps_fixed)
                except np.linalg.LinAlgError:
                    return 1e25, np.zeros_like(p)
            if not np.isfinite(val) or not np.all(np.isfinite(grad)):
                return 1e25, np.zeros_like(p)
            return -val, -grad

        p0 = np.concatenate([kernel.theta, [np.log(s2)]])
        p = self._optimise(objective, p0, self.online_maxiter)
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
        self._require_fitted()
        st = self._state
        return st.chol @ (st.d_inv @ st.r)

    @property
    def q_cov_(self) -> np.ndarray:
        """Covariance of q(b): ``L_b D^-1 L_b'``."""
        self._require_fitted()
        st = self._state
        cov = st.chol @ st.d_inv @ st.chol.T
        return 0.5 * (cov + cov.T)

    @property
    def n_buffered(self) -> int:
        """Samples waiting for the next streaming step."""
        return len(self._buffer)

    # ----------------------------------------------------------------- prediction
    def predict(self, xi, u) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance of the latent f at (xi (N, b), u (N, m)) (eq. 14)."""
        self._require_fitted()
        k = self.kernel_
        xi, u, _ = check_batch(xi, u, input_dim=k.input_dim, action_dim=k.action_dim)
        st = self._state
        ub = ubar(u)
        kdiag = (ub * ub) @ st.var
        if st.size == 0:
            return np.zeros(xi.shape[0]), kdiag
        ksb = np.einsum("inj,ni,ji->nj", _components_at(st, xi), ub, st.ub)  # [N, M]
        mean = ksb @ st.w
        var = kdiag - np.einsum("nm,nm->n", ksb @ st.q, ksb)
        return mean, np.maximum(var, 0.0)

    def predict_affine(self, xi) -> tuple[np.ndarray, np.ndarray]:
        """Affine form at xi (N, b): ``b`` (N, m+1), ``Sigma`` (N, m+1, m+1) (eqs. 20-21).

        ``mean = b . ubar``, ``var = ubar' Sigma ubar``; Sigma is symmetrised and made PSD
        (a round-off negative eigenvalue is lifted to zero by a tiny diagonal shift).
        """
        self._require_fitted()
        st = self._state
        if not (isinstance(xi, np.ndarray) and xi.dtype == np.float64 and xi.ndim == 2
                and xi.shape[1] == st.inv_ls.shape[1] and xi.shape[0] > 0
                and np.isfinite(xi).all()):  # fast path for well-formed arrays
            xi = check_matrix(xi, "xi", ncols=self.kernel_.input_dim)
            if xi.shape[0] == 0:
                raise ValueError("xi must contain at least one row")
        n, c = xi.shape[0], st.var.shape[0]
        sigma = np.zeros((n, c, c))
        sigma[:, np.arange(c), np.arange(c)] = st.var
        if st.size == 0:
            return np.zeros((n, c)), sigma
        kt = _components_at(st, xi).transpose(1, 0, 2) * st.ub.T  # [N, m+1, M] (eq. 21)
        coef = kt @ st.w
        sigma -= kt @ st.q @ kt.transpose(0, 2, 1)
        sigma = 0.5 * (sigma + sigma.transpose(0, 2, 1))
        return coef, _clip_psd(sigma)


def _components_at(st: _State, xi: np.ndarray) -> np.ndarray:
    """RBF components ``k_i(xi_n, b_j)`` (m+1, N, M), inducing side cached in the state.

    Same arithmetic as ``ADPKernel.components`` (scaled squared distances, clipped at 0).
    """
    a = xi[None, :, :] * st.inv_ls[:, None, :]  # [m+1, N, b]
    d = np.einsum("inb,inb->in", a, a)[:, :, None] + st.ns[:, None, :]
    d -= 2.0 * (a @ st.xs.transpose(0, 2, 1))
    np.maximum(d, 0.0, out=d)
    d *= -0.5
    np.exp(d, out=d)
    d *= st.var[:, None, None]
    return d


def _online_bound_and_grad(kernel, s2, prior, xi_p, ub_p, idx, f, ma, z, eps):
    """Bui's online bound and its gradient w.r.t. ``concat(theta, [log s2])``.

    Pool ``p`` = old points (first ``ma``) then the batch ``f``; ``b = p[idx]``; ``eps`` fixed.
    """
    kpp = _gram(kernel, xi_p, ub_p)
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


def _scale(z: np.ndarray) -> float:
    v = float(np.var(z)) if z.shape[0] > 1 else 0.0
    if not v > 1e-12:
        v = max(float(np.mean(z * z)), 1.0)
    return v


def _noise_init(z: np.ndarray) -> float:
    return 0.1 * _scale(z)
