"""Chance-constrained HOCBF safety filter as a second-order cone program (paper eq. 05, 49).

Decision variable ``u`` (action, ``m``), ``ubar = [1, u]``. For every barrier ``k``

    minimise    1/2 ||u - u_nom||^2
    subject to  a0_k + a_k @ u - ||G_k @ ubar|| >= 0        (one second-order cone each)
                low <= u <= high

with ``a0 + a @ u = F0 ubar + S + alpha_r(psi_{r-1}) + b' ubar`` (nominal part plus learned
mean) and ``G = beta L'`` for the learned covariance ``Sigma = L L'`` (standard deviation, as in
Castaneda et al. 2021; the paper's eq. 05 writes the variance). With ``G = 0`` this is the
HOCBF-QP of eq. 04.

Clarabel's standard form is ``min 1/2 x'Px + q'x  s.t.  Ax + s = b, s in K``. The rows are

    box:       [ I; -I] u + s = [high; -low],             s in R_+^{2m}
    barrier k: [-a_k'; -G_k[:, 1:]] u + s = [a0_k; G_k[:, 0]],   s in SOC(m + 2)

The matrices keep a dense sparsity pattern so each solver object is built once and only its
values are updated (``DefaultSolver.update``). If the problem is infeasible or the solve fails,
the fallback maximises the worst margin ``t`` within the bounds (another cone program,
``min -t + eps/2 ||u - u_nom||^2``) and the result is flagged; the returned action is always
finite and inside the bounds.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import clarabel
import numpy as np
import scipy.sparse as sp

_SOLVED = ("Solved", "AlmostSolved")


@dataclass(frozen=True)
class SOCPResult:
    """Outcome of one filter solve.

    Attributes
    ----------
    u : ndarray of shape (m,)
        Applied action, finite and within the bounds.
    feasible : bool
        True when the chance-constrained problem was solved; False means ``u`` is the fallback.
    status : str
        Solver status (``"Solved"``, ``"fallback:<status>"``, ``"invalid_input"``, ...).
    margins : ndarray of shape (K,)
        ``a0 + a @ u - ||G ubar||`` at ``u`` (NaN for invalid constraints).
    solve_time_s : float
        Wall time of the solve(s).
    """

    u: np.ndarray
    feasible: bool
    status: str
    margins: np.ndarray
    solve_time_s: float


def _settings(tol: float) -> clarabel.DefaultSettings:
    s = clarabel.DefaultSettings()
    s.verbose = False
    s.presolve_enable = False  # needed for data updates
    s.chordal_decomposition_enable = False
    s.tol_gap_abs = tol
    s.tol_gap_rel = tol
    s.tol_feas = tol
    s.max_iter = 100
    return s


class SOCPFilter:
    """Reusable clarabel cone programs for the safety filter.

    Parameters
    ----------
    action_low, action_high : array_like of shape (m,)
        Finite action bounds, ``low < high``.
    n_constraints : int
        Number of barriers ``K`` (one cone each).
    qp_solver : str or None
        Backend for the plain QP case (``G = 0``): None uses clarabel directly (cached solver
        object); a name is passed to ``qpsolvers.solve_qp(..., solver=name)``.
    tol : float
        Clarabel feasibility and gap tolerances.
    fallback_regularization : float
        ``eps`` of the fallback objective (tie-break towards ``u_nom``).
    """

    def __init__(
        self,
        action_low,
        action_high,
        n_constraints: int = 1,
        *,
        qp_solver: str | None = None,
        tol: float = 1e-9,
        fallback_regularization: float = 1e-4,
    ):
        low = np.asarray(action_low, dtype=np.float64).ravel()
        high = np.asarray(action_high, dtype=np.float64).ravel()
        if low.shape != high.shape or low.size == 0:
            raise ValueError(
                f"action_low and action_high must have the same non-empty shape. "
                f"Got: {low.shape} and {high.shape}"
            )
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(low < high)):
            raise ValueError(
                f"action bounds must be finite with action_low < action_high. Got: {low}, {high}"
            )
        if not isinstance(n_constraints, (int, np.integer)) or n_constraints < 1:
            raise ValueError(f"n_constraints must be a positive integer. Got: {n_constraints!r}")
        if qp_solver is not None:
            import qpsolvers

            if qp_solver not in qpsolvers.available_solvers:
                raise ValueError(
                    f"qp_solver {qp_solver!r} is not available; installed: "
                    f"{qpsolvers.available_solvers}"
                )
        self.low, self.high = low, high
        self.m = low.size
        self.n_constraints = int(n_constraints)
        self.qp_solver = qp_solver
        self.tol = float(tol)
        self.fallback_regularization = float(fallback_regularization)
        self._solvers: dict[str, clarabel.DefaultSolver] = {}
        self._buffers: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        m = self.m
        self._box_A = np.vstack([np.eye(m), -np.eye(m)])
        self._box_b = np.concatenate([high, -low])

    def __getstate__(self) -> dict:
        """Pickle/deepcopy without the clarabel solver objects (not picklable; rebuilt on the
        next solve with the same data layout)."""
        state = self.__dict__.copy()
        state["_solvers"] = {}
        return state

    # ------------------------------------------------------------------ problem data
    def _data(self, kind: str, u_nom, a0, a, G):
        """Dense (A transposed, b, q) for ``kind`` in {"qp", "socp", "fallback"} (reused)."""
        m, K = self.m, self.n_constraints
        buf = self._buffers.get(kind)
        if buf is None:
            nx = m + 1 if kind == "fallback" else m
            rows = 2 * m + (K if kind == "qp" else K * (m + 2))
            At = np.zeros((nx, rows))  # A transposed: At.ravel() is A's CSC value order
            At[:m, : 2 * m] = self._box_A.T
            b = np.zeros(rows)
            b[: 2 * m] = self._box_b
            buf = self._buffers[kind] = (At, b)
        At, b = buf
        A = At.T  # a view
        if kind == "qp":
            A[2 * m :, :] = -a
            b[2 * m :] = a0
        else:
            for k in range(K):
                r0 = 2 * m + k * (m + 2)
                A[r0, :m] = -a[k]
                A[r0 + 1 : r0 + m + 2, :m] = -G[k][:, 1:]
                if kind == "fallback":
                    A[r0, m] = 1.0
                b[r0] = a0[k]
                b[r0 + 1 : r0 + m + 2] = G[k][:, 0]
        if kind == "fallback":
            eps = self.fallback_regularization
            q = np.concatenate([-eps * u_nom, [-1.0]])
        else:
            q = -u_nom
        return At, b.copy(), q

    def _cones(self, kind: str):
        m, K = self.m, self.n_constraints
        if kind == "qp":
            return [clarabel.NonnegativeConeT(2 * m + K)]
        return [clarabel.NonnegativeConeT(2 * m)] + [clarabel.SecondOrderConeT(m + 2)] * K

    def _run(self, kind: str, u_nom, a0, a, G):
        At, b, q = self._data(kind, u_nom, a0, a, G)
        solver = self._solvers.get(kind)
        if solver is None:
            if kind == "fallback":
                P = np.diag(np.concatenate([np.full(self.m, self.fallback_regularization), [0.0]]))
            else:
                P = np.eye(self.m)
            A_pattern = sp.csc_matrix(np.ones_like(At.T))
            A_pattern.data[:] = At.ravel()
            solver = clarabel.DefaultSolver(
                sp.csc_matrix(np.triu(P)), q, A_pattern, b, self._cones(kind), _settings(self.tol)
            )
            self._solvers[kind] = solver
        else:
            solver.update(q=q, b=b, A=At.ravel())
        sol = solver.solve()
        return np.asarray(sol.x, dtype=np.float64), str(sol.status)

    def _run_qpsolvers(self, u_nom, a0, a):
        import qpsolvers

        x = qpsolvers.solve_qp(
            sp.csc_matrix(np.eye(self.m)),
            -u_nom,
            sp.csc_matrix(-a),
            a0,
            lb=self.low,
            ub=self.high,
            solver=self.qp_solver,
        )
        if x is None:
            return np.full(self.m, np.nan), "Failed"
        return np.asarray(x, dtype=np.float64), "Solved"

    # ------------------------------------------------------------------ public
    def margins(self, u, a0, a, G=None) -> np.ndarray:
        """``a0 + a @ u - ||G ubar||`` for every barrier."""
        out = np.asarray(a0, dtype=np.float64) + np.asarray(a, dtype=np.float64) @ u
        if G is not None:
            G = np.asarray(G, dtype=np.float64)
            Gu = G[:, :, 0] + G[:, :, 1:] @ u
            out = out - np.sqrt(np.einsum("ki,ki->k", Gu, Gu))
        return out

    def solve(self, u_nom, a0, a, G=None, backup=None) -> SOCPResult:
        """Filter ``u_nom`` (never raises for finite-shaped inputs; NaN -> flagged fallback).

        Parameters
        ----------
        u_nom : array_like of shape (m,)
        a0 : array_like of shape (K,)
            Action-free part of each constraint.
        a : array_like of shape (K, m)
            Action coefficients.
        G : array_like of shape (K, m+1, m+1) or None
            Cone matrices ``beta L'``; None (or all zero) gives the plain QP.
        backup : array_like of shape (m,), zero-argument callable returning one, or None
            Action applied (clipped to the bounds, status ``"backup:..."``) when the program is
            infeasible or fails; the callable is only evaluated then. None, or a backup that
            is not finite, has the wrong shape or raises: the max-worst-margin fallback.
        """
        t0 = time.perf_counter()
        m, K = self.m, self.n_constraints
        u_nom = np.asarray(u_nom, dtype=np.float64).ravel()
        a0 = np.asarray(a0, dtype=np.float64).ravel()
        a = np.asarray(a, dtype=np.float64).reshape(K, m)
        G = None if G is None else np.asarray(G, dtype=np.float64).reshape(K, m + 1, m + 1)
        if u_nom.shape != (m,) or a0.shape != (K,):
            raise ValueError(f"u_nom must have shape ({m},) and a0 ({K},)")

        # sanitise: invalid constraints become vacuous, a NaN nominal becomes the box centre
        total = u_nom.sum() + a0.sum() + a.sum() + (0.0 if G is None else G.sum())
        if np.isfinite(total):
            valid = np.ones(K, dtype=bool)
            nom_ok = True
        else:
            valid = np.isfinite(a0) & np.all(np.isfinite(a), axis=1)
            if G is not None:
                valid &= np.all(np.isfinite(G), axis=(1, 2))
            nom_ok = bool(np.all(np.isfinite(u_nom)))
        invalid = not (nom_ok and np.all(valid))
        if not nom_ok:
            u_nom = np.clip(np.zeros(m), self.low, self.high)
        u_nom_c = np.clip(u_nom, self.low, self.high)
        if not np.all(valid):
            a0 = np.where(valid, a0, 1.0)
            a = np.where(valid[:, None], a, 0.0)
            if G is not None:
                G = np.where(valid[:, None, None], G, 0.0)

        if not invalid:
            marg = self.margins(u_nom_c, a0, a, G)
            return self.solve_checked(u_nom, u_nom_c, a0, a, G, marg, t0, backup)
        return self._fallback("invalid_input", u_nom, u_nom_c, a0, a, G, valid, t0, backup)

    def solve_checked(
        self, u_nom, u_nom_c, a0, a, G, marg, t0: float, backup=None
    ) -> SOCPResult:
        """:meth:`solve` after validation: every input finite and of the right shape (float64),
        ``u_nom_c`` the clipped ``u_nom`` and ``marg = margins(u_nom_c, a0, a, G)``; ``t0``
        the ``perf_counter`` start. Lets a caller that already checked its data skip the
        checks; identical results."""
        m = self.m
        if bool((marg >= 0.0).all()):  # the (clipped) nominal action is safe: inactive filter
            return SOCPResult(u_nom_c, True, "inactive", marg, time.perf_counter() - t0)
        use_qp = G is None or not G.any()
        Gz = np.zeros((self.n_constraints, m + 1, m + 1)) if G is None else G
        try:
            if use_qp and self.qp_solver is not None:
                x, status = self._run_qpsolvers(u_nom, a0, a)
            else:
                x, status = self._run("qp" if use_qp else "socp", u_nom, a0, a, Gz)
            u = x[:m]
            if status in _SOLVED and math.isfinite(float(u.sum())):
                u = np.clip(u, self.low, self.high)
                marg = self.margins(u, a0, a, G)
                if bool((marg >= -1e-6 * (1.0 + np.abs(a0))).all()):
                    return SOCPResult(u, True, status, marg, time.perf_counter() - t0)
                status = "constraint_violated"
        except Exception as exc:  # never raise in the control loop
            status = f"error:{type(exc).__name__}"
        return self._fallback(status, u_nom, u_nom_c, a0, a, G, None, t0, backup)

    def _backup_action(self, backup) -> np.ndarray | None:
        """The clipped backup action, or None if there is none usable."""
        if backup is None:
            return None
        try:
            ub = np.array(backup() if callable(backup) else backup, dtype=np.float64)
        except Exception:  # a failing backup must not stop the loop
            return None
        if ub.shape != (self.m,) or not np.all(np.isfinite(ub)):
            return None
        return np.clip(ub, self.low, self.high)

    def _fallback(self, status, u_nom, u_nom_c, a0, a, G, valid, t0, backup=None) -> SOCPResult:
        m = self.m
        u = self._backup_action(backup)
        if u is not None:
            status = f"backup:{status}"
        else:  # maximise the worst margin within the bounds
            u = u_nom_c
            Gz = np.zeros((self.n_constraints, m + 1, m + 1)) if G is None else G
            try:
                x, fb_status = self._run("fallback", u_nom, a0, a, Gz)
                if fb_status in _SOLVED and np.all(np.isfinite(x[:m])):
                    u = np.clip(x[:m], self.low, self.high)
                status = f"fallback:{status}" if status != "invalid_input" else status
            except Exception as exc:
                status = f"fallback_failed:{type(exc).__name__}"
        marg = self.margins(u, a0, a, G)
        if valid is not None:
            marg = np.where(valid, marg, np.nan)
        return SOCPResult(u, False, status, marg, time.perf_counter() - t0)
