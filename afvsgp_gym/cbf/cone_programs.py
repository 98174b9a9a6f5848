"""The filter's cone programs in clarabel's standard form, one reusable solver per size.

Clarabel solves ``min 1/2 x'Px + q'x  s.t.  Ax + s = b, s in K``. For ``k`` constraints on
``m`` actions (paper eq. 05; eq. 04 when there is no cone) the rows are

    box:       [ I; -I] u + s = [high; -low],                   s in R_+^{2m}
    "qp":      -a u + s = a0,                                    s in R_+^k
    "socp":    [-a_i; -G_i[:, 1:]] u + s = [a0_i; G_i[:, 0]],   s in SOC(m + 2), one per i

and the max-worst-margin programs ``"fallback_qp"`` / ``"fallback_socp"`` add a variable
``t`` (``min -t + eps/2 ||u - u_nom||^2``, ``+t`` in each constraint's first row).

A solver object is built once per ``(kind, k)`` (on first use, or ahead of the control
loop by :meth:`ConePrograms.prepare`) and afterwards only its values change
(``DefaultSolver.update``; this needs presolve off). The box block keeps its two non-zeros
per column; a constraint's rows are dense in ``u`` (a Cholesky factor ``G`` is triangular,
an eigen-factor is not). Data equilibration is off: a reused solver would keep the scaling of
the instance it was built with, so with it on the same instance gave different answers (at the
solver's tolerance) from a fresh and from a reused solver. Off, an instance's answer depends on
the instance only, whichever solver object solves it.
"""

from __future__ import annotations

import clarabel
import numpy as np
import scipy.sparse as sp

SOLVED = ("Solved", "AlmostSolved")
KINDS = ("qp", "socp", "fallback_qp", "fallback_socp")


def settings(tol: float, strictly_convex: bool = False) -> clarabel.DefaultSettings:
    """Clarabel settings for reusable solvers with gap and feasibility tolerance ``tol``.

    ``strictly_convex``: the objective's ``P`` is positive definite (``P = I``: the filter's
    programs), so the KKT matrix ``[P, A'; A, -W'W]`` is quasi-definite at every iterate and
    its LDL' factorisation exists without the static regularisation (turned off; the
    dynamic regularisation stays on)."""
    s = clarabel.DefaultSettings()
    s.verbose = False
    s.presolve_enable = False  # required for data updates
    s.equilibrate_enable = False  # a reused solver would keep its first instance's scaling
    s.static_regularization_enable = not strictly_convex
    s.chordal_decomposition_enable = False
    s.tol_gap_abs = tol
    s.tol_gap_rel = tol
    s.tol_feas = tol
    s.max_iter = 100
    return s


class ConePrograms:
    """Clarabel solvers of the filter's programs for action bounds ``low``, ``high``, cached
    by ``(kind, k)``; :meth:`solve` builds or updates one and returns ``(x, status)``."""

    def __init__(self, low: np.ndarray, high: np.ndarray, tol: float, fallback_eps: float):
        self.low, self.high = low, high
        self.m = low.size
        self.tol = float(tol)
        self.fallback_eps = float(fallback_eps)
        self._solvers: dict[tuple[str, int], clarabel.DefaultSolver] = {}
        self._data: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}

    def __getstate__(self) -> dict:
        """Pickle/deepcopy without the solver objects (not picklable; rebuilt when needed)."""
        state = self.__dict__.copy()
        state["_solvers"] = {}
        return state

    def clear(self) -> None:
        """Drop every cached solver (the next solves build new ones)."""
        self._solvers.clear()

    # ------------------------------------------------------------------ layout
    def _rows_per_constraint(self, kind: str) -> int:
        return 1 if kind.endswith("qp") else self.m + 2

    def _layout(self, kind: str, k: int):
        """Buffers ``(Ad, b)``: ``Ad[j]`` holds column j of A (CSC value order), built once."""
        key = (kind, k)
        buf = self._data.get(key)
        if buf is None:
            m, rows = self.m, self._rows_per_constraint(kind)
            Ad = np.zeros((m, 2 + k * rows))
            Ad[:, 0], Ad[:, 1] = 1.0, -1.0
            b = np.empty(2 * m + k * rows)
            b[:m], b[m : 2 * m] = self.high, -self.low
            buf = self._data[key] = (Ad, b)
        return buf

    def _fill(self, kind: str, a0, a, G):
        """A's values (CSC order) and b for the constraint data."""
        m, k = self.m, a0.size
        rows = self._rows_per_constraint(kind)
        Ad, b = self._layout(kind, k)
        blk = Ad[:, 2:].reshape(m, k, rows)
        blk[:, :, 0] = -a.T
        bb = b[2 * m :].reshape(k, rows)
        bb[:, 0] = a0
        if rows > 1:
            blk[:, :, 1:] = -G[:, :, 1:].transpose(2, 0, 1)
            bb[:, 1:] = G[:, :, 0]
        values = Ad.ravel()
        if kind.startswith("fallback"):
            values = np.concatenate([values, np.ones(k)])
        return values, b

    def _matrix(self, kind: str, k: int, values: np.ndarray) -> sp.csc_matrix:
        m, rows = self.m, self._rows_per_constraint(kind)
        box = np.stack([np.arange(m), m + np.arange(m)], axis=1)
        con = np.broadcast_to(2 * m + np.arange(k * rows), (m, k * rows))
        indices = np.concatenate([box, con], axis=1).ravel()
        indptr = np.arange(m + 1) * (2 + k * rows)
        if kind.startswith("fallback"):  # column of t: +1 in each constraint's first row
            indices = np.concatenate([indices, 2 * m + rows * np.arange(k)])
            indptr = np.append(indptr, indptr[-1] + k)
        n_rows = 2 * m + k * rows
        nx = m + 1 if kind.startswith("fallback") else m
        return sp.csc_matrix((values, indices, indptr), shape=(n_rows, nx))

    def _cones(self, kind: str, k: int) -> list:
        if kind.endswith("qp"):
            return [clarabel.NonnegativeConeT(2 * self.m + k)]
        return [clarabel.NonnegativeConeT(2 * self.m)] + [
            clarabel.SecondOrderConeT(self.m + 2)
        ] * k

    def _hessian(self, kind: str) -> sp.csc_matrix:
        if kind.startswith("fallback"):
            return sp.diags(np.append(np.full(self.m, self.fallback_eps), 0.0), format="csc")
        return sp.identity(self.m, format="csc")

    def _linear(self, kind: str, u_nom: np.ndarray) -> np.ndarray:
        if kind.startswith("fallback"):
            return np.append(-self.fallback_eps * u_nom, -1.0)
        return -u_nom

    def prepare(self, kind: str, sizes) -> None:
        """Build the solvers of program ``kind`` for every ``k`` in ``sizes`` now, so that the
        control loop only updates them (a build costs ~3x an update and solve). The
        placeholder data are never solved: only the sparsity pattern is kept."""
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}. Got: {kind!r}")
        m = self.m
        for k in sizes:
            k = int(k)
            if k < 1:
                raise ValueError(f"sizes must be >= 1. Got: {k}")
            if (kind, k) not in self._solvers:
                G = None if kind.endswith("qp") else np.ones((k, m + 1, m + 1))
                self._build(kind, np.zeros(m), np.ones(k), np.ones((k, m)), G)

    def _build(self, kind: str, u_nom, a0, a, G) -> clarabel.DefaultSolver:
        values, b = self._fill(kind, a0, a, G)
        solver = clarabel.DefaultSolver(
            self._hessian(kind), self._linear(kind, u_nom),
            self._matrix(kind, a0.size, values), b, self._cones(kind, a0.size),
            settings(self.tol, strictly_convex=not kind.startswith("fallback")),
        )
        self._solvers[(kind, a0.size)] = solver
        return solver

    # ------------------------------------------------------------------ solve
    def solve(self, kind: str, u_nom, a0, a, G=None) -> tuple[np.ndarray, str]:
        """Solve program ``kind`` (one of :data:`KINDS`) for the data; ``(x, status)`` with
        ``x`` the solver's primal solution (``u``, then ``t`` for a fallback)."""
        solver = self._solvers.get((kind, a0.size))
        if solver is None:
            solver = self._build(kind, u_nom, a0, a, G)
        else:
            values, b = self._fill(kind, a0, a, G)
            solver.update(q=self._linear(kind, u_nom), b=b, A=values)
        sol = solver.solve()
        return np.asarray(sol.x, dtype=np.float64), str(sol.status)
