"""A bank of K independent AFVSGP learners updated together (one per barrier).

Each learner ``k`` is exactly an :class:`~afvsgp_gym.gp.AFVSGP` (own kernel, noise, inducing
set, window of the last ``P`` samples with forgetting ``phi``; paper eqs. 20-32), but the
state of all K lives in stacked arrays so a control step costs one set of numpy/LAPACK calls
for all learners, not K:

    S_k <- phi S_k + k k' - phi^P k_old k_old',   r_k <- phi r_k + z k - phi^P z_old k_old
    b_k(xi) = Kt B_k r_k / s2_k,   Sigma_k(xi) = diag(s_k) - Kt (K_oo^-1 - B_k) Kt'     (eq. 20)

with ``B_k = (K_oo,k + S_k / s2_k)^-1``, computed in whitened form (``L^-1 S L^-T / s2``,
triangular solves only; ``I + L^-1 S L^-T / s2 >= I`` factors stably however ill-conditioned
``K_oo + S / s2`` is). Inducing sets have up to ``num_inducing`` points;
a learner with fewer is padded with inert slots (identity block in ``K_oo``, zero kernel
columns), which leaves every posterior quantity unchanged. The rare inducing-set changes
(eqs. 27-30: add, and replace by the eq. 28 score) run per learner.

:class:`~afvsgp_gym.gp.AFVSGP` is a bank of one learner with scikit-learn style ``fit`` /
``update`` / ``predict``; :meth:`AFVSGPBank.from_learners` stacks fitted ones, then
:meth:`update` takes the K samples of a step and :meth:`predict_affine` predicts for the
learners whose prediction is needed (e.g. the barriers near an obstacle).

The per-step arithmetic (the window step of every learner, the predictions, the eqs. 27-28
decision on a new inducing point, the installation of a new inducing point with its factor
and inverse of ``K_oo``) runs compiled when ``afvsgp_gym.gp._bank`` is built (the backend
``"auto"`` or ``"compiled"``, see :mod:`afvsgp_gym._compiled`; the same formulas in C with
scipy's BLAS and LAPACK, one call each in place of tens of numpy calls; the kernel's exponent
from the differences to the inducing points, its exponential by the core's own vectorised
exp, within 1.5 ulp; for a learner predicted at consecutive steps the update carries its
whitened statistics ``A = L^-1 S L^-T``, ``A += scale (l l' - phi^P l_old l_old')`` with
``l = L^-1 k_new``, so that its prediction factors ``I + A / s2`` without solving ``A``
afresh), else, or with the backend ``"numpy"``, in numpy; the rare cases (skipped samples,
a kernel exponent that overflows, a failed factorisation) always run in numpy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.linalg.blas import dtrsm
from scipy.linalg.lapack import dpotrf, dtrtri

from afvsgp_gym import _compiled
from afvsgp_gym.gp._linalg import jittered_cholesky
from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["AFVSGPBank", "BankSettings", "FittedState"]

_core = _compiled.extension("bank")


@dataclass(frozen=True)
class BankSettings:
    """The AFVSGP settings every learner of a bank shares (see :class:`~afvsgp_gym.gp.AFVSGP`)."""

    window: int
    forgetting: float
    num_inducing: int
    add_threshold: float
    swap_margin: float
    refresh_every: int | None
    adapt_inducing: bool


@dataclass(frozen=True)
class FittedState:
    """One learner right after its offline fit: hyperparameters, absolute jitter on ``K_oo``,
    inducing set ``(xi_o, ub_o)`` and the window samples ``(xi, ub, z)`` oldest first."""

    kernel: ADPKernel
    noise_variance: float
    jitter: float
    xi_o: np.ndarray
    ub_o: np.ndarray
    xi: np.ndarray
    ub: np.ndarray
    z: np.ndarray


class _Candidate(NamedTuple):
    """A new inducing point's data (eqs. 29-30): the point it replaces (None: appended),
    ``L^-1 k_new``, its window column ``k(x, window)``, new row of ``S``, the new pivot of
    ``chol(K_oo)`` squared (``d`` + jitter), ``S``'s new diagonal entry and entry of ``r``."""

    drop: int | None
    lvec: np.ndarray
    col: np.ndarray
    srow: np.ndarray
    dd: float
    sdiag: float
    r_new: float


#: The arrays the compiled core holds in its state (its names -> the bank's attributes; the
#: per-step outputs k_new, kss, resid are the bank's ``_step_out``).
_CORE_ARRAYS = (("ind_xit", "_ind_xit"), ("log_var", "log_var"), ("inv_ls2", "inv_ls2"),
                ("ubt", "_ubt"), ("var", "var"), ("koo_inv", "_koo_inv"), ("stats", "_stats"),
                ("scale", "_scale"), ("wk", "_wk"), ("wz", "_wz"), ("wxt", "_wxt"),
                ("wubt", "_wubt"), ("work", "_work"), ("head", "_head"), ("count", "_count"),
                ("n_seen", "n_seen_"), ("fresh", "_fresh"), ("since", "_since_refresh"),
                ("noise_variance", "noise_variance"), ("l_oo", "_l_oo"), ("lsl", "_lsl"),
                ("white", "_white"), ("l_d", "_l_d"), ("cvec", "_cvec"), ("ind_ub", "_ind_ub"),
                ("koo", "_koo"), ("n_added", "n_added_"), ("n_removed", "n_removed_"),
                ("pow_rev", "_pow_rev"))

#: Per-learner arrays (leading axis K), concatenated by :meth:`AFVSGPBank.stack`.
_STACKED = ("inv_ls2", "var", "_var_diag", "log_var", "noise_variance", "jitter", "n_inducing_",
            "_ind_xit", "_ind_ub", "_amat", "_ubt", "_koo", "_l_oo", "_koo_inv", "_stats",
            "_scale", "_wz", "_wk", "_wxt", "_wubt", "_head", "_count", "_l_d", "_cvec",
            "_fresh", "_lsl", "_white", "n_seen_", "n_added_", "n_removed_")


class AFVSGPBank:
    """K AFVSGP learners in stacked arrays (see the module docstring).

    Per learner ``k``: :meth:`inducing` (its inducing set), :meth:`window_samples` (its window),
    :meth:`statistics` (``S``, ``r``),
    :meth:`conditioning` (of ``K_oo`` and ``K_oo + S/s2``).

    Parameters
    ----------
    settings : BankSettings
    states : sequence of FittedState
        One per learner (same input and action dimensions).
    max_inducing_candidates : int or None
        Bound on the learners whose new sample is examined as an inducing point in one
        :meth:`update` (eqs. 27-30, O(P M) each; the candidates with the largest relative eq.
        27 residual go first, the others are considered again with their next samples): it
        bounds the worst-case step time. None examines every candidate, exactly as K
        separate learners do.
    backend : str or Backend
        Where the per-step arithmetic runs: ``"auto"`` (default) in the compiled core when it
        is built, ``"numpy"`` in numpy, ``"compiled"`` in the compiled core (``ImportError``
        when it was not built), or as a resolved ``Backend`` says (the filter's); see
        :mod:`afvsgp_gym._compiled`. Settable later.

    Attributes
    ----------
    compiled : bool
        True when the per-step arithmetic runs in the compiled core.
    n_learners : int
    n_inducing_ : ndarray of int, shape (K,)
        Current inducing-set sizes.
    n_seen_, n_added_, n_removed_ : ndarray of int, shape (K,)
    """

    def __init__(self, settings: BankSettings, states: Sequence[FittedState],
                 max_inducing_candidates: int | None = None, backend="auto"):
        if not states:
            raise ValueError("states must hold at least one fitted learner state")
        self._set_settings(settings, states[0].kernel, max_inducing_candidates)
        self.backend = backend
        K, P, b, c, mp = len(states), self.window, self.input_dim, self._c, self._mp
        self.n_learners = K
        for k, st in enumerate(states):
            if (st.kernel.input_dim, st.kernel.action_dim) != (b, c - 1):
                raise ValueError(f"states[{k}] has other input/action dimensions")
            if len(st.xi_o) > mp:
                raise ValueError(f"states[{k}] has more than num_inducing={mp} inducing points")
        # hyperparameters
        self.inv_ls2 = np.array([st.kernel._inv_ls ** 2 for st in states])  # (K, c, b)
        self.var = np.array([st.kernel._var for st in states])  # (K, c)
        self.log_var = np.log(self.var)
        self._var_diag = self.var[:, :, None] * np.eye(self._c)  # diag(s) of eq. 20
        self.noise_variance = np.array([float(st.noise_variance) for st in states])
        self.jitter = np.array([float(st.jitter) for st in states])
        self.kernels = [st.kernel.clone() for st in states]
        # inducing sets (padded)
        self.n_inducing_ = np.zeros(K, dtype=int)
        self._ind_xit = np.zeros((K, b, mp))  # inducing inputs by dimension (see _ind_xi)
        self._ind_ub = np.zeros((K, mp, c))
        self._amat = np.zeros((K, c * mp, b + 1))  # exponent rows, see _set_inducing
        self._ubt = np.zeros((K, c, mp))
        self._koo = np.zeros((K, mp, mp))
        self._l_oo = np.zeros((K, mp, mp))
        self._koo_inv = np.zeros((K, mp, mp))
        # statistics [r, S] with a per-learner scale (forgetting folded in), the window ring
        self._stats = np.zeros((K, mp, mp + 1))
        self._scale = np.ones(K)
        self._wz = np.zeros((K, P))
        self._wk = np.zeros((K, P, mp))
        self._wxt = np.zeros((K, b, P))  # window xi and ubar by slot, transposed
        self._wubt = np.zeros((K, c, P))
        self._head = np.full(K, -1)
        self._count = np.zeros(K, dtype=int)
        # whitened posterior cache: chol(I + L^-1 S L^-T / s2) and its solve with L^-1 r / s2
        self._l_d = np.zeros((K, mp, mp))
        self._cvec = np.zeros((K, mp))
        self._fresh = np.zeros(K, dtype=bool)
        # compiled core: A = L^-1 S L^-T of the learners predicted since their last update
        self._lsl, self._white = self._new_whitened(K)
        self.n_seen_ = np.zeros(K, dtype=int)
        self.n_added_ = np.zeros(K, dtype=int)
        self.n_removed_ = np.zeros(K, dtype=int)
        for k, st in enumerate(states):
            n = min(len(st.z), P)
            xi, ub, z = st.xi[-n:], st.ub[-n:], st.z[-n:]
            self._wz[k, :n] = z
            self._wxt[k, :, :n] = xi.T
            self._wubt[k, :, :n] = ub.T
            self._count[k], self._head[k] = n, n - 1
            self.n_seen_[k] = n
            koo = st.kernel._gram(st.xi_o, st.ub_o)
            koo[np.diag_indices_from(koo)] += self.jitter[k]
            self._set_inducing(k, st.xi_o, st.ub_o, koo, jittered_cholesky(koo, name="K_oo"))
            self._wk[k, :n, : len(st.xi_o)] = st.kernel._gram(xi, ub, st.xi_o, st.ub_o)
            self._rebuild_stats(k)
        self._stagger()

    def _set_settings(self, settings: BankSettings, kernel: ADPKernel,
                      max_inducing_candidates: int | None) -> None:
        if max_inducing_candidates is not None and int(max_inducing_candidates) < 1:
            raise ValueError(f"max_inducing_candidates must be >= 1 or None, got "
                             f"{max_inducing_candidates}")
        self.settings = settings
        self.max_inducing_candidates = max_inducing_candidates
        self.window = P = int(settings.window)
        self.forgetting = phi = float(settings.forgetting)
        self.num_inducing = int(settings.num_inducing)
        self.add_threshold = float(settings.add_threshold)
        self._add_floor = max(self.add_threshold, 1e-6)  # d > max(a, 1e-6) k_ss (eq. 27)
        self.swap_margin = float(settings.swap_margin)
        self.adapt_inducing = bool(settings.adapt_inducing)
        self._refresh_every = P if settings.refresh_every is None else int(settings.refresh_every)
        self.input_dim = kernel.input_dim
        self.action_dim = kernel.action_dim
        self._c = self.action_dim + 1
        self._mp = self.num_inducing
        self._phi, self._phi_p, self._inv_phi = phi, phi ** P, 1.0 / phi
        self._pow_rev = phi ** np.arange(P - 1, -1, -1, dtype=float)  # phi**(P-1-i)

    def _stagger(self) -> None:
        """Spread the periodic rebuilds so that at most a few learners rebuild in one step."""
        K = self.n_learners
        self._dims = (K, self.input_dim, self._c, self._mp, self.window)
        self._work = np.empty(max(K * self._c * self._mp, self._c * self.window))  # core's scratch
        self._step_out = self._new_step_out()
        self._since_refresh = (np.arange(K) * self._refresh_every) // K
        self._synced = bool((self._head == self._head[0]).all()
                            and (self._count == self._count[0]).all())
        self._cstate = None  # the arrays are new: the core takes them again

    @property
    def compiled(self) -> bool:
        """True when the per-step arithmetic runs in the compiled core."""
        return self._compiled

    @property
    def backend(self) -> str:
        """``"auto"``, ``"numpy"`` or ``"compiled"`` (see the class docstring); settable."""
        return self._backend

    @backend.setter
    def backend(self, value) -> None:
        resolved = _compiled.resolve(value, ("bank",))
        self._backend, self._compiled = resolved.name, resolved.bank

    @property
    def _ind_xi(self) -> np.ndarray:
        """The inducing inputs (K, Mp, b): a view of their storage by dimension, (K, b, Mp),
        from which the compiled core reads each dimension's values contiguously."""
        return self._ind_xit.transpose(0, 2, 1)

    def _new_step_out(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The core's per-step outputs: k_new (K, Mp), k_ss (K,), the eq. 27 residuals (K,)
        (read within the step)."""
        K = self.n_learners
        return np.empty((K, self._mp)), np.empty(K), np.empty(K)

    def _new_whitened(self, K: int) -> tuple[np.ndarray, np.ndarray]:
        """The compiled core's whitened statistics ``A = L^-1 S L^-T`` (K, Mp, Mp) and the
        (K,) flags of the learners whose ``A`` is current (none)."""
        return np.zeros((K, self._mp, self._mp)), np.zeros(K, dtype=bool)

    def _core_state(self):
        """The compiled core's state of this bank: its arrays, taken once (on the first call
        after they were allocated) and held by the core (see ``_bank.state``)."""
        state = self._cstate
        if state is None:
            arrays = {name: getattr(self, attr) for name, attr in _CORE_ARRAYS}
            arrays["k_new"], arrays["kss"], arrays["resid"] = self._step_out
            state = self._cstate = _core.state(
                self._dims, arrays, (self._inv_phi, self._phi_p, self._add_floor,
                                     self.swap_margin, self._refresh_every))
        return state

    def __getstate__(self) -> dict:
        """Pickle (and deepcopy) without the compiled core's state (it holds the arrays'
        buffers; a copy takes its own arrays again)."""
        state = dict(self.__dict__)
        state["_cstate"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        """Unpickle; a bank pickled where the core was built runs numpy where it is not."""
        self.__dict__.update(state)
        self._cstate = None
        if "_ind_xi" in state:  # pickled when the inducing inputs were stored by point
            self._ind_xit = np.ascontiguousarray(self.__dict__.pop("_ind_xi").transpose(0, 2, 1))
        if "_step_out" not in state:  # pickled before the per-step outputs were kept
            self._step_out = self._new_step_out()
        if "_lsl" not in state:  # pickled before the whitened statistics were kept
            self._lsl, self._white = self._new_whitened(self.n_learners)
        if "_backend" not in state:  # pickled when the switch was compiled=None/True/False
            self._backend = "auto" if self._compiled else "numpy"
        if _core is None:
            self._compiled = False

    @classmethod
    def stack(cls, banks: Sequence[AFVSGPBank],
              max_inducing_candidates: int | None = None,
              backend="auto") -> AFVSGPBank:
        """One bank holding copies of the learners of ``banks`` (equal settings), in order
        (``backend``: see the class docstring)."""
        if not banks:
            raise ValueError("banks must hold at least one AFVSGPBank")
        first = banks[0]
        for i, bk in enumerate(banks):
            if bk.settings != first.settings:
                raise ValueError(f"banks[{i}] has other settings than banks[0]: "
                                 f"{bk.settings} != {first.settings}")
            if (bk.input_dim, bk.action_dim) != (first.input_dim, first.action_dim):
                raise ValueError(f"banks[{i}] has other input/action dimensions")
        out = cls.__new__(cls)
        out._set_settings(first.settings, first.kernels[0], max_inducing_candidates)
        out.backend = backend
        for name in _STACKED:
            setattr(out, name, np.concatenate([getattr(bk, name) for bk in banks]))
        out.kernels = [k.clone() for bk in banks for k in bk.kernels]
        out.n_learners = len(out.kernels)
        out._stagger()
        return out

    @classmethod
    def from_learners(cls, learners: Sequence, max_inducing_candidates: int | None = None,
                      backend="auto") -> AFVSGPBank:
        """One bank holding copies of the state of fitted :class:`~afvsgp_gym.gp.AFVSGP`
        ``learners`` (each a bank of one; equal settings; see ``max_inducing_candidates`` in
        the class docstring)."""
        if not learners:
            raise ValueError("learners must hold at least one fitted AFVSGP")
        for k, lr in enumerate(learners):
            if not isinstance(getattr(lr, "_bank", None), AFVSGPBank):
                raise ValueError(f"learners[{k}] must be a fitted AFVSGP")
        try:
            return cls.stack([lr._bank for lr in learners], max_inducing_candidates, backend)
        except ValueError as exc:
            raise ValueError(f"learners: {exc}") from None

    # ------------------------------------------------------------------ per-learner state
    def _set_inducing(self, k: int, xo: np.ndarray, ubo: np.ndarray, koo: np.ndarray,
                      low: np.ndarray) -> None:
        """Install inducing set ``(xo, ubo)`` with ``K_oo`` (jitter included) and its factor."""
        m, mp, b = len(xo), self._mp, self.input_dim
        il2 = self.inv_ls2[k]  # (c, b)
        self.n_inducing_[k] = m
        self._ind_xi[k] = 0.0
        self._ind_ub[k] = 0.0
        self._ind_xi[k, :m] = xo
        self._ind_ub[k, :m] = ubo
        # exponent of k_i(x, o_j) = log s_i - |o_j/l_i|^2/2 + (o_j/l_i^2).x - (1/(2 l_i^2)).x^2:
        # rows [o_j/l_i^2, log s_i - |o_j/l_i|^2/2]; the x^2 term is the same for every j
        a = self._amat[k].reshape(self._c, mp, b + 1)
        a[:] = 0.0
        s = xo[None, :, :] * il2[:, None, :]  # (c, m, b)
        a[:, :m, :b] = s
        a[:, :m, b] = self.log_var[k][:, None] - 0.5 * np.einsum("imd,md->im", s, xo)
        self._ubt[k] = 0.0
        self._ubt[k, :, :m] = ubo.T
        eye = np.eye(mp)
        self._koo[k] = eye
        self._koo[k, :m, :m] = koo
        self._l_oo[k] = eye
        self._l_oo[k, :m, :m] = low
        self._koo_inv[k] = eye
        self._set_koo_inv(k)

    def _set_koo_inv(self, k: int) -> None:
        """``K_oo^-1`` of learner ``k`` from its factor (``L^-T L^-1``); marks it stale."""
        m = self.n_inducing_[k]
        low = self._l_oo[k, :m, :m]
        linv, info = dtrtri(low, lower=1)
        if info != 0:
            linv = np.linalg.inv(low)
        self._koo_inv[k, :m, :m] = linv.T @ linv
        self._fresh[k] = self._white[k] = False

    def _weights(self, k: int) -> np.ndarray:
        """``phi**age`` of window slots ``[0, count)`` of learner ``k``."""
        head, cnt, rev = int(self._head[k]), int(self._count[k]), self._pow_rev
        if head + 1 == cnt:  # slots [0, head]: ages head..0
            return rev[self.window - cnt :]
        return np.concatenate((rev[self.window - 1 - head :], rev[: cnt - head - 1]))

    def _rebuild_stats(self, k: int) -> None:
        """``[r, S]`` of learner ``k`` from its stored window (the periodic drift refresh)."""
        cnt = self._count[k]
        rows = self._wk[k, :cnt]
        wk = rows * self._weights(k)[:, None]
        self._stats[k, :, 0] = wk.T @ self._wz[k, :cnt]
        self._stats[k, :, 1:] = wk.T @ rows
        self._scale[k] = 1.0
        self._fresh[k] = self._white[k] = False

    def _renormalise(self, k: int) -> None:
        if self._scale[k] != 1.0:
            self._stats[k] *= 1.0 / self._scale[k]
            self._scale[k] = 1.0
            self._white[k] = False

    def inducing(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Learner ``k``'s inducing set: features (M, b) and actions (M, m) (copies)."""
        m = int(self.n_inducing_[k])
        return self._ind_xi[k, :m].copy(), self._ind_ub[k, :m, 1:].copy()

    def window_samples(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Learner ``k``'s window, oldest first: features (n, b), actions (n, m) and eq. 48
        samples (n,), ``n <= window`` (copies; the data a re-fit of its hyperparameters
        would see)."""
        n, P = int(self._count[k]), self.window
        slots = (int(self._head[k]) - n + 1 + np.arange(n)) % P
        return (self._wxt[k][:, slots].T.copy(), self._wubt[k][1:, slots].T.copy(),
                self._wz[k, slots].copy())

    def statistics(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Learner ``k``'s weighted statistics (eq. 20): ``S = K_ox Lambda K_xo`` (M, M) and
        ``r = K_ox Lambda z`` (M,) (copies)."""
        m = int(self.n_inducing_[k])
        st = self._stats[k] / self._scale[k]
        return st[:m, 1 : m + 1].copy(), st[:m, 0].copy()

    def conditioning(self) -> tuple[np.ndarray, np.ndarray]:
        """(K,) 2-norm condition numbers of ``K_oo`` and ``K_oo + S/s2`` of every learner."""
        c_oo, c_sig = np.empty(self.n_learners), np.empty(self.n_learners)
        for k in range(self.n_learners):
            m = self.n_inducing_[k]
            koo = self._koo[k, :m, :m]
            sig = koo + self._stats[k, :m, 1 : m + 1] / (self.noise_variance[k] * self._scale[k])
            c_oo[k], c_sig[k] = np.linalg.cond(koo), np.linalg.cond(sig)
        return c_oo, c_sig

    # ------------------------------------------------------------------ kernel rows
    def _kt(self, rows, xi: np.ndarray) -> np.ndarray:
        """``Kt`` (k, m+1, Mp) of learners ``rows`` at their points ``xi`` (k, b) (eq. 21)."""
        n, b = xi.shape
        feat = np.empty((n, 1, b + 1))
        feat[:, 0, :b] = xi
        feat[:, 0, b] = 1.0
        amat = self._amat if rows is None else self._amat[rows]
        il2 = self.inv_ls2 if rows is None else self.inv_ls2[rows]
        e = np.matmul(feat, amat.transpose(0, 2, 1)).reshape(n, self._c, self._mp)
        e += np.matmul(il2, (-0.5 * xi * xi)[:, :, None])  # (n, c, 1): the x^2 term
        if not math.isfinite(float(e.sum())):  # huge |xi|: x^2 overflows in the expansion
            idx = np.arange(self.n_learners) if rows is None else np.asarray(rows)
            e = self._exponent_direct(idx, xi)
        np.exp(e, out=e)
        e *= self._ubt if rows is None else self._ubt[rows]
        return e

    def _exponent_direct(self, rows: np.ndarray, xi: np.ndarray) -> np.ndarray:
        """``log k_i(xi_j, o)`` (n, m+1, Mp) from the differences, for points so far out that
        the expansion overflows (the kernel underflows to 0 there)."""
        with np.errstate(over="ignore"):
            d = xi[:, None, :] - self._ind_xi[rows]  # (n, Mp, b)
            e = self.log_var[rows][:, :, None] - 0.5 * np.einsum(
                "jmd,jid->jim", d * d, self.inv_ls2[rows])
        return e

    # ------------------------------------------------------------------ prediction
    def _stats_block(self, idx: np.ndarray, kt_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``inv = 1 / s2`` (n,) and the (n, Mp, Mp + q + 1) blocks ``[S, Kt', r / s2]`` of
        learners ``idx`` with their ``q`` kernel rows ``kt_rows`` (n, q, Mp): the transposed
        block ``[S; Kt; r' / s2]`` of each is Fortran-ordered, as :meth:`_whiten` takes it."""
        n, q, mp = kt_rows.shape
        inv = 1.0 / (self.noise_variance[idx] * self._scale[idx])
        st = self._stats[idx]
        buf = np.empty((n, mp, mp + q + 1))
        buf[:, :, :mp] = st[:, :, 1:]
        buf[:, :, mp : mp + q] = kt_rows.transpose(0, 2, 1)
        np.multiply(st[:, :, 0], inv[:, None], out=buf[:, :, mp + q])
        return inv, buf

    def _whiten(self, k: int, xt: np.ndarray, inv: float) -> np.ndarray:
        """Eq. 20 in whitened form (triangular solves only) for learner ``k`` from the
        Fortran-ordered rows ``xt = [S; Kt; r' / s2]`` (Mp + q + 1, Mp), with ``L = chol(K_oo)``:
        ``xt`` becomes ``[S L^-T; G'; (L^-1 r / s2)']`` in place (``G = L^-1 Kt'``); unless
        fresh, the posterior cache is refreshed: ``D = I + L^-1 S L^-T / s2`` (``>= I``),
        ``L_D = chol(D)``, ``c = L_D^-1 L^-1 r / s2``. Returns ``[H'; c']`` (q + 1, Mp),
        ``H = L_D^-1 G``."""
        mp = self._mp
        upper = self._l_oo[k].T  # L' (Fortran-ordered): X L' = B solves in place, no copy
        dtrsm(1.0, upper, xt, 1, 0, 0, 0, 1)
        if self._fresh[k]:
            return dtrsm(1.0, self._l_d[k].T, xt[mp:], 1, 0, 0, 0, 0)
        # (S L^-T)' = L^-1 S (S symmetric); dpotrf reads the lower triangle only
        d = dtrsm(inv, upper, xt[:mp].T, 1, 0, 0, 0, 0)  # L^-1 S L^-T / s2
        d.T.reshape(-1)[:: mp + 1] += 1.0
        l_d, info = dpotrf(d, lower=1, clean=1, overwrite_a=1)
        if info != 0:
            d = dtrsm(inv, upper, xt[:mp].T, 1, 0, 0, 0, 0)
            d += np.eye(mp)
            l_d = jittered_cholesky(d, name="I + L^-1 S L^-T / s2")
        self._l_d[k] = l_d
        out = dtrsm(1.0, l_d, xt[mp:], 1, 1, 1, 0, 0)
        self._cvec[k] = out[-1]
        self._fresh[k] = True
        return out

    def _moments(self, idx: np.ndarray, gt: np.ndarray, hc: np.ndarray):
        """``b = H' c`` (n, m+1) and ``Sigma = diag(s) - G'G + H'H`` (n, m+1, m+1) from
        ``G'`` (n, m+1, Mp) and ``[H'; c']`` (n, m+2, Mp) (eq. 20 in whitened form): one Gram
        of ``[H'; c']`` gives ``H'H`` and ``H'c``; learner ``idx[j]`` gives row ``j``'s prior
        variances ``s``."""
        c = gt.shape[1]
        f = np.matmul(hc, hc.transpose(0, 2, 1))
        sig = np.subtract(f[:, :c, :c], np.matmul(gt, gt.transpose(0, 2, 1)))
        sig += sig.transpose(0, 2, 1)
        sig *= 0.5
        sig += self._var_diag[idx]
        return f[:, :c, c], sig

    def predict_affine(self, xi: np.ndarray, rows: np.ndarray | None = None):
        """``b`` (k, m+1) and ``Sigma`` (k, m+1, m+1) of the learners ``rows`` (default all)
        at their points ``xi`` (k, b): mean ``b . ubar`` and variance ``ubar' Sigma ubar``
        of ``Delta B^(r)`` (eq. 20). ``xi`` must be finite (the caller checks)."""
        idx = np.arange(self.n_learners) if rows is None else np.asarray(rows, dtype=np.int64)
        xi = np.asarray(xi, dtype=np.float64).reshape(len(idx), self.input_dim)
        c, mp = self._c, self._mp
        n = len(idx)
        if self._compiled:
            bvec, sig = np.empty((n, c)), np.empty((n, c, c))
            rc = _core.predict(self._core_state(), n, np.ascontiguousarray(idx),
                               np.ascontiguousarray(xi), bvec, sig)
            if rc == 0:
                return bvec, sig
        kt = self._kt(rows, xi)
        inv, buf = self._stats_block(idx, kt)
        hc = np.empty((n, c + 1, mp))  # [H'; c'] per row
        for j, k in enumerate(idx):
            hc[j] = self._whiten(k, buf[j].T, inv[j])
        gt = buf[:, :, mp : mp + c].transpose(0, 2, 1)
        return self._moments(idx, gt, hc)

    def predict_points(self, k: int, xi: np.ndarray):
        """``b`` (N, m+1) and ``Sigma`` (N, m+1, m+1) of learner ``k`` at N finite points
        ``xi`` (N, b) (eq. 20): one kernel product, two triangular solves for all points."""
        xi = np.asarray(xi, dtype=np.float64)
        n, b = xi.shape
        c, mp = self._c, self._mp
        feat = np.empty((n, b + 1))
        feat[:, :b] = xi
        feat[:, b] = 1.0
        e = (feat @ self._amat[k].T).reshape(n, c, mp)
        e += ((-0.5 * xi * xi) @ self.inv_ls2[k].T)[:, :, None]  # the x^2 term
        if not math.isfinite(float(e.sum())):  # huge |xi|: x^2 overflows in the expansion
            e = np.concatenate([self._exponent_direct(np.array([k]), x[None]) for x in xi])
        kt = np.exp(e)
        kt *= self._ubt[k]
        idx = np.array([k])
        inv, buf = self._stats_block(idx, kt.reshape(1, n * c, mp))
        hc = self._whiten(k, buf[0].T, inv[0])
        gt = buf[0, :, mp : mp + n * c].T.reshape(n, c, mp)
        hcn = np.empty((n, c + 1, mp))  # [H'; c'] per point
        hcn[:, :c] = hc[: n * c].reshape(n, c, mp)
        hcn[:, c] = hc[n * c]
        return self._moments(np.full(n, k), gt, hcn)

    # ------------------------------------------------------------------ update
    def update(self, xi: np.ndarray, u: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Stream one sample into every learner: ``(xi[k], u, z[k])`` for learner ``k``
        (eqs. 24-28). Learners whose ``xi[k]`` or ``z[k]`` is not finite are left unchanged.
        Returns the (K,) mask of learners updated. ``ValueError`` (nothing changed) on wrong
        shapes or a non-finite ``u``."""
        K, b = self.n_learners, self.input_dim
        xi = np.asarray(xi, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64).ravel()
        z = np.asarray(z, dtype=np.float64).ravel()
        if xi.shape != (K, b) or z.shape != (K,) or u.shape != (self.action_dim,):
            raise ValueError(
                f"update needs xi ({K}, {b}), u ({self.action_dim},), z ({K},). Got: "
                f"{xi.shape}, {u.shape}, {z.shape}")
        if self._synced and self._compiled:
            done = self._update_compiled(xi, u, z)
            if done is not None:
                return done
        total = xi.sum(axis=1)
        total += z
        if math.isfinite(float(total.sum()) + float(u.sum())):  # every sample finite
            ok, rows, idx, sel = np.empty(K, dtype=bool), None, None, slice(None)
            ok.fill(True)
        else:
            if not np.isfinite(u).all():
                raise ValueError("u contains NaN or inf")
            ok = np.isfinite(total)
            if not ok.any():
                return ok
            rows, idx, sel = None, None, slice(None)
            if not ok.all():
                rows = idx = sel = np.flatnonzero(ok)
                xi, z = xi[rows], z[rows]
        ub = np.empty(self._c)
        ub[0] = 1.0
        ub[1:] = u
        kt = self._kt(rows, xi)  # (k, c, Mp)
        k_new = np.matmul(ub, kt)  # (k, Mp)
        kss = self.var[sel] @ (ub * ub)
        # sliding window with forgetting (eqs. 25-26, docs/equations.md); phi S in the scale
        scale = self._scale[sel] * self._inv_phi
        self._scale[sel] = scale
        if rows is None and self._synced:
            self._slide_synced(xi, ub, z, k_new, scale)
        else:
            self._synced = False  # a learner skipped a sample: the rings may differ from here
            self._slide(np.arange(K) if idx is None else idx, rows, sel, xi, ub, z, k_new, scale)
        self.n_seen_[sel] += 1
        self._fresh[sel] = self._white[sel] = False
        since = self._since_refresh[sel]  # a view when every learner is updated
        since += 1
        if rows is not None:
            self._since_refresh[rows] = since
        if since.max() >= self._refresh_every:
            idx = np.arange(K) if idx is None else idx
            for k in idx[since >= self._refresh_every]:
                self._rebuild_stats(k)
                self._since_refresh[k] = 0
        if scale.max() > 1e100:
            idx = np.arange(K) if idx is None else idx
            for k in idx[scale > 1e100]:
                self._renormalise(k)
        if self.adapt_inducing:
            self._add_candidates(idx, sel, xi, ub, kss, k_new)
        return ok

    def _update_compiled(self, xi: np.ndarray, u: np.ndarray, z: np.ndarray) -> np.ndarray | None:
        """:meth:`update` of learners at one ring position in the compiled core (the window
        step, the bookkeeping, the eq. 27 residuals); the periodic rebuilds and inducing-set
        changes it reports due run here. None (nothing changed) when a sample is not finite
        or a kernel exponent overflows: the numpy path takes them."""
        K = self.n_learners
        ub = np.empty(self._c)
        ub[0] = 1.0
        ub[1:] = u
        xi, z = np.ascontiguousarray(xi), np.ascontiguousarray(z)
        k_new, kss, resid = self._step_out
        rc, n_cand, best, refresh, renormalise = _core.update(self._core_state(), xi, ub, z)
        if rc != 0:
            return None
        if refresh:
            for k in np.flatnonzero(self._since_refresh >= self._refresh_every):
                self._rebuild_stats(k)
                self._since_refresh[k] = 0
        if renormalise:
            for k in np.flatnonzero(self._scale > 1e100):
                self._renormalise(k)
        if n_cand and self.adapt_inducing:
            if self.max_inducing_candidates == 1:  # the core found the one to offer
                self._consider_add(best, xi[best], ub, float(kss[best]), k_new[best])
            else:
                self._add_candidates(None, slice(None), xi, ub, kss, k_new, resid)
        return np.ones(K, dtype=bool)

    def _add_candidates(self, idx, sel, xi: np.ndarray, ub: np.ndarray, kss: np.ndarray,
                        k_new: np.ndarray, d: np.ndarray | None = None) -> None:
        """Offer the new samples whose eq. 27 residual ``d = k_ss - k' K_oo^-1 k`` (weight
        1; computed unless given) exceeds ``add_threshold k_ss``, ``1e-6 k_ss`` and the noise
        variance to :meth:`_consider_add` (largest relative residual first, at most
        ``max_inducing_candidates``)."""
        if d is None:
            ktk = np.matmul(self._koo_inv[sel], k_new[:, :, None])
            d = kss - np.matmul(k_new[:, None, :], ktk).ravel()
        cand = d > np.maximum(self._add_floor * kss, self.noise_variance[sel])  # kss > 0
        if cand.any():
            idx = np.arange(self.n_learners) if idx is None else idx
            order = np.flatnonzero(cand)
            if self.max_inducing_candidates is not None:
                order = order[np.argsort(-d[order] / kss[order])]
                order = order[: self.max_inducing_candidates]
            for j in order:
                self._consider_add(int(idx[j]), xi[j], ub, float(kss[j]), k_new[j])

    def _rank2(self, n: int, k_new: np.ndarray, z: np.ndarray, scale: np.ndarray,
               full: bool) -> tuple[np.ndarray, np.ndarray]:
        """Factors ``left`` (n, Mp, 2), ``right`` (n, 2, Mp + 1) of the window's rank-2
        change of ``[r, S]``: the new sample (column 0, scaled) in; column 1 is left to the
        caller (the sample leaving a full window: uninitialised if ``full``, else zero)."""
        new = np.empty if full else np.zeros
        left = new((n, self._mp, 2))
        right = new((n, 2, self._mp + 1))
        left[:, :, 0] = k_new
        np.multiply(z, scale, out=right[:, 0, 0])
        np.multiply(k_new, scale[:, None], out=right[:, 0, 1:])
        return left, right

    def _slide_synced(self, xi: np.ndarray, ub: np.ndarray, z: np.ndarray, k_new: np.ndarray,
                      scale: np.ndarray) -> None:
        """The window step of every learner when all share one ring position (the usual
        case): one slot for all, so basic slicing in place of per-learner indices."""
        cnt, P = int(self._count[0]), self.window
        full = cnt == P
        slot = (int(self._head[0]) + 1) % P if full else cnt
        left, right = self._rank2(self.n_learners, k_new, z, scale, full)
        if full:
            k_old = self._wk[:, slot]
            left[:, :, 1] = k_old
            f = -self._phi_p * scale
            np.multiply(self._wz[:, slot], f, out=right[:, 1, 0])
            np.multiply(k_old, f[:, None], out=right[:, 1, 1:])
        self._stats += np.matmul(left, right)
        self._wk[:, slot] = k_new
        self._wz[:, slot] = z
        self._wxt[:, :, slot] = xi
        self._wubt[:, :, slot] = ub
        self._head[:] = slot
        if not full:
            self._count += 1

    def _slide(self, idx: np.ndarray, rows, sel, xi: np.ndarray, ub: np.ndarray, z: np.ndarray,
               k_new: np.ndarray, scale: np.ndarray) -> None:
        """The window step of learners ``idx`` (``rows``/``sel``: None/slice or ``idx``),
        each at its own ring position."""
        cnt = self._count[sel]
        full = cnt == self.window
        slot = np.where(full, self._head[sel] + 1, cnt)
        slot[slot == self.window] = 0
        stats = self._stats[sel] if rows is not None else self._stats
        # the new sample in, the sample leaving a full window out: one batched rank-2 product
        left, right = self._rank2(len(idx), k_new, z, scale, bool(full.all()))
        if full.any():
            fi, fs = idx[full], slot[full]
            k_old = self._wk[fi, fs]
            left[full, :, 1] = k_old
            f = -self._phi_p * scale[full]
            right[full, 1, 0] = self._wz[fi, fs] * f
            right[full, 1, 1:] = k_old * f[:, None]
        stats += np.matmul(left, right)
        if rows is not None:
            self._stats[rows] = stats
        self._wk[idx, slot] = k_new
        self._wz[idx, slot] = z
        self._wxt[idx, :, slot] = xi
        self._wubt[idx, :, slot] = ub
        self._head[sel] = slot
        self._count[sel] = cnt + ~full

    # ------------------------------------------------------------------ inducing set
    def _window_column(self, k: int, xi: np.ndarray, ub: np.ndarray) -> np.ndarray:
        """``k(x_t, (xi, ub))`` for learner ``k``'s window samples (slot order), from the
        differences: ``sum_i ub_i ub_t,i s_i exp(-|(x_t - xi) / l_i|^2 / 2)``."""
        cnt = self._count[k]
        d = self._wxt[k, :, :cnt] - xi[:, None]  # (b, cnt)
        d *= d
        e = np.matmul(-0.5 * self.inv_ls2[k], d)  # (c, cnt), <= 0
        e += self.log_var[k][:, None]
        np.exp(e, out=e)
        e *= self._wubt[k, :, :cnt]
        return ub @ e

    def _consider_add(self, k: int, xi: np.ndarray, ub: np.ndarray, kss: float,
                      k_new: np.ndarray) -> bool:
        """Add the newest sample of learner ``k`` as an inducing point (eqs. 29-30),
        replacing the least informative one (eq. 28) when the set is full. True if the
        inducing set changed. The new point goes last, or into the dropped point's slot."""
        find = self._candidate_compiled if self._compiled else self._candidate
        cand = find(k, xi, ub, kss, k_new)
        self._white[k] = False  # the decision may have renormalised [r, S]
        if cand is None:
            return False
        self._install(k, xi, ub, kss, k_new, cand)
        return True

    def _candidate(self, k: int, xi: np.ndarray, ub: np.ndarray, kss: float,
                   k_new: np.ndarray) -> _Candidate | None:
        """The decision on learner ``k``'s newest sample as an inducing point (eqs. 27-28):
        None when its residual ``d = k_ss - |L^-1 k|^2`` is not above ``1e-6 k_ss``, or, with
        a full set, its eq. 28 score does not beat the least informative point's by
        ``swap_margin k_ss``; else what :meth:`_install` needs. Renormalises the statistics
        once the residual passes."""
        m = int(self.n_inducing_[k])
        low = self._l_oo[k, :m, :m]
        kn = k_new[:m]
        lvec = dtrsm(1.0, low, kn[:, None], 0, 1, 0, 0, 0)[:, 0]
        d = kss - float(lvec @ lvec)  # the same residual, from the factor (stable)
        if not d > 1e-6 * kss:
            return None
        self._renormalise(k)
        cnt = self._count[k]
        col = self._window_column(k, xi, ub)
        lc = self._weights(k) * col
        srow = lc @ self._wk[k, :cnt, :m]  # the new row of S (eq. 30)
        sdiag = float(lc @ col)
        dd = d + self.jitter[k]  # the new pivot of chol(K_oo) squared
        drop = None
        if m + 1 > self.num_inducing:
            # eq. 28 on the enlarged set: K_e^-1 by the bordered inverse (w = K_oo^-1 k_new)
            st = self._stats[k]
            w = self._koo_inv[k, :m, :m] @ kn
            kinv = np.empty((m + 1, m + 1))
            np.multiply.outer(w, w / dd, out=kinv[:m, :m])
            kinv[:m, :m] += self._koo_inv[k, :m, :m]
            kinv[m, :m] = kinv[:m, m] = -w / dd
            kinv[m, m] = 1.0 / dd
            se = np.empty((m + 1, m + 1))
            se[:m, :m] = st[:m, 1 : m + 1]
            se[m, :m] = se[:m, m] = srow
            se[m, m] = sdiag
            score = ((kinv @ se) * kinv).sum(axis=1) / np.diag(kinv)
            j = int(np.argmin(score[:m]))  # eq. 28: least informative old point
            if not score[m] - score[j] > self.swap_margin * kss:
                return None  # not informative enough: state unchanged
            drop = j
        r_new = float(lc @ self._wz[k, :cnt])
        return _Candidate(drop, lvec, col, srow, dd, sdiag, r_new)

    def _candidate_compiled(self, k: int, xi: np.ndarray, ub: np.ndarray, kss: float,
                            k_new: np.ndarray) -> _Candidate | None:
        """:meth:`_candidate` in the compiled core."""
        m, cnt = int(self.n_inducing_[k]), int(self._count[k])
        lvec, col, srow = np.empty(self._mp), np.empty(self.window), np.empty(self._mp)
        code, drop, dd, sdiag, r_new = _core.candidate(
            self._core_state(), k, m, int(self._head[k]), cnt, float(kss),
            float(self.jitter[k]), np.ascontiguousarray(xi), ub, np.ascontiguousarray(k_new),
            lvec, col, srow)
        if code == 0:
            return None
        return _Candidate(drop if code == 2 else None, lvec[:m], col[:cnt], srow[:m], dd,
                          sdiag, r_new)

    def _install(self, k: int, xi: np.ndarray, ub: np.ndarray, kss: float, k_new: np.ndarray,
                 cand: _Candidate) -> None:
        """Install learner ``k``'s newest sample as inducing point (eqs. 29-30): last, or in
        the slot of the point ``cand.drop``; ``K_oo``, its factor and inverse, ``[r, S]``,
        the kernel rows and the window's kernel column follow (the copies and the inverse in
        the compiled core when the bank runs there)."""
        m = int(self.n_inducing_[k])
        drop = cand.drop
        pos, mm = (m, m + 1) if drop is None else (drop, m)
        self._white[k] = False
        self._set_exponent_rows(k, pos, xi)
        kss_jit = kss + self.jitter[k]
        if self._compiled:
            if _core.install(self._core_state(), k, m, pos, drop is not None,
                             int(self._count[k]), float(kss_jit), float(cand.sdiag),
                             float(cand.r_new), float(cand.dd), xi, ub, k_new, cand.srow,
                             cand.col, cand.lvec) == 0:
                self.n_inducing_[k] = mm
                return
        else:
            self._install_copies(k, m, pos, mm, xi, ub, kss_jit, k_new, cand)
        koo, lo = self._koo[k], self._l_oo[k]
        if drop is not None:
            low_n, info = dpotrf(koo[:mm, :mm], lower=1, clean=1)  # O(M^3 / 3)
            if info != 0:
                low_n = jittered_cholesky(koo[:mm, :mm], name="K_oo")
            lo[:mm, :mm] = low_n
        self.n_inducing_[k] = mm
        self._set_koo_inv(k)

    def _set_exponent_rows(self, k: int, pos: int, xi: np.ndarray) -> None:
        """The numpy path's exponent rows of learner ``k``'s inducing point ``pos`` at ``xi``
        (see :meth:`_set_inducing`): ``[xi / l_i^2, log s_i - |xi / l_i|^2 / 2]``."""
        sx = self.inv_ls2[k] * xi  # (c, b)
        a = self._amat[k].reshape(self._c, self._mp, -1)
        a[:, pos, :-1] = sx
        a[:, pos, -1] = self.log_var[k] - 0.5 * (sx @ xi)

    def _install_copies(self, k: int, m: int, pos: int, mm: int, xi: np.ndarray,
                        ub: np.ndarray, kss_jit: float, k_new: np.ndarray,
                        cand: _Candidate) -> None:
        """:meth:`_install`'s copies in numpy (the compiled core's ``install`` makes the same):
        the new point's inputs, its rows and columns of ``K_oo`` and ``[r, S]``, its kernel
        column over the window, with append the bordered factor's row."""
        kn, srow = k_new[:m], cand.srow
        self.n_added_[k] += 1
        if cand.drop is None:  # the new point goes last
            krow, srow = np.append(kn, kss_jit), np.append(srow, cand.sdiag)
        else:  # the new point takes the dropped point's slot
            self.n_removed_[k] += 1
            krow = kn.copy()
            krow[pos] = kss_jit
            srow = srow.copy()
            srow[pos] = cand.sdiag
        self._ind_xi[k, pos] = xi
        self._ind_ub[k, pos] = ub
        self._ubt[k, :, pos] = ub
        koo = self._koo[k]
        koo[pos, :mm] = koo[:mm, pos] = krow
        st = self._stats[k]
        st[pos, 0] = cand.r_new
        st[pos, 1 : mm + 1] = st[:mm, pos + 1] = srow
        self._wk[k, : self._count[k], pos] = cand.col
        if cand.drop is None:  # the bordered factor
            lo = self._l_oo[k]
            lo[pos, :pos] = cand.lvec
            lo[pos, pos] = math.sqrt(cand.dd)
