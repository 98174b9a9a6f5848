"""Chance-constrained HOCBF safety filter as a second-order cone program (paper eq. 05, 49).

Decision variable ``u`` (action, ``m``), ``ubar = [1, u]``. For every barrier ``i`` passed
to a call (any number ``k >= 0``; the caller may leave out barriers far from every obstacle)

    minimise    1/2 ||u - u_nom||^2
    subject to  a0_i + a_i @ u - ||G_i @ ubar|| >= 0        (one second-order cone each)
                low <= u <= high

with ``a0 + a @ u = F0 ubar + S + alpha_r(psi_{r-1}) + b' ubar`` (nominal part plus learned
mean) and ``G = beta L'`` for the learned covariance ``Sigma = L L'`` (standard deviation, as in
Castaneda et al. 2021; the paper's eq. 05 writes the variance). With ``G = 0`` (or None) this
is the HOCBF-QP of eq. 04.

:meth:`SOCPFilter.solve` tries, in order: the clipped proposal (returned as is when it
satisfies every constraint: status ``"inactive"``); an exact fast path
(:mod:`afvsgp_gym.cbf.fastpath`: one half-space, any number of half-spaces, one cone, each
with the box; one cone by the compiled projection,
:func:`afvsgp_gym.cbf.binding_cones.project_cones_box`, first when it is built; with several
cones, the compiled search of the binding cones,
:func:`afvsgp_gym.cbf.binding_cones.solve_binding_set`, when it is built, then the projection
onto the one farthest from the proposal) whose answer is used only when its KKT certificate
holds (status ``"certified:<path>"``, ``"certified:cones"`` with several binding cones);
clarabel (:mod:`afvsgp_gym.cbf.cone_programs`, status ``"Solved"`` or ``"AlmostSolved"``).
With several cones clarabel first solves the program over a working set of them (the
farthest and the most violated at the fast path's answer, enlarged by the most violated at
each answer, ``WORKING_SET_ADD`` at a time): an answer that satisfies every constraint is the
optimum of the whole program (whose feasible set lies inside the working set's), an
infeasible working set proves the whole program infeasible; after ``WORKING_SET_ROUNDS``
rounds the whole program is solved. If the program is infeasible or the solve fails, a
backup action or the action maximising the worst margin (``min -t + eps/2 ||u - u_nom||^2``)
is returned, flagged infeasible; for half-spaces (the QP) that program is solved on a working
set of them (the Farkas certificate's) and KKT-certified
(:meth:`SOCPFilter._fast_max_margin`), clarabel solving it when that fails. The returned
action is always finite and inside the bounds, and one returned as feasible satisfies every
constraint to ``1e-8`` of the constraint's scale
(:func:`afvsgp_gym.cbf.fastpath.constraint_scales`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from afvsgp_gym import _compiled
from afvsgp_gym.cbf import binding_cones, fastpath
from afvsgp_gym.cbf.cone_programs import SOLVED, ConePrograms

#: A returned feasible action satisfies ``c_i(u) >= -FEASIBILITY_TOL * scale_i``.
FEASIBILITY_TOL = 1e-8
#: Working-set rounds of clarabel with several cones before the whole program is solved.
WORKING_SET_ROUNDS = 3
#: Cones added to the working set per round: the most violated ones (relative to scale).
WORKING_SET_ADD = 2
#: Most binding cones of the compiled several-cones path (:mod:`binding_cones`).
BINDING_CONES_MAX = 5
#: Working-set rounds of the QP's least-distance fast path before clarabel.
QP_WORKING_SET_ROUNDS = 4
_ZERO = np.zeros(1)  # a multiplier's start (read only)
_ONE = np.ones(1, dtype=bool)  # one binding cone (read only)


@dataclass(frozen=True)
class SOCPResult:
    """Outcome of one filter solve.

    Attributes
    ----------
    u : ndarray of shape (m,)
        Applied action, finite and within the bounds.
    feasible : bool
        True when the chance-constrained problem was solved; False means ``u`` is the
        backup action or the max-worst-margin fallback.
    status : str
        ``"inactive"`` (the clipped proposal is safe), ``"certified:halfspace"``,
        ``"certified:polyhedron"``, ``"certified:cone"``, ``"certified:cones"`` (exact fast
        path, KKT-certified; the last with several binding cones),
        clarabel's ``"Solved"`` / ``"AlmostSolved"``, ``"backup:<why>"``,
        ``"fallback:<why>"`` (``<why>``: clarabel's status, or ``infeasible`` for a Farkas
        certificate of the QP from the fast path) or ``"invalid_input"``.
    margins : ndarray of shape (k,)
        ``a0 + a @ u - ||G ubar||`` at ``u`` (NaN for invalid constraints).
    solve_time_s : float
        Wall time of the call.
    """

    u: np.ndarray
    feasible: bool
    status: str
    margins: np.ndarray
    solve_time_s: float


class SOCPFilter:
    """The safety filter's cone program for any number of constraints per call.

    Parameters
    ----------
    action_low, action_high : array_like of shape (m,)
        Finite action bounds, ``low < high``.
    n_constraints : int or None
        Accepted for compatibility and checked (an integer >= 0); every call may pass any
        number of constraints.
    qp_solver : str or None
        Backend for the plain QP case (``G = 0``) when the fast path does not certify: None
        uses clarabel directly (cached solver); a name is passed to
        ``qpsolvers.solve_qp(..., solver=name)``.
    tol : float
        Clarabel feasibility and gap tolerances.
    fallback_regularization : float
        ``eps`` of the fallback objective (tie-break towards ``u_nom``).
    fast_path : bool
        Use the certified fast paths (False: clarabel for every active call; for reference
        and benchmarks).
    backend : str or Backend
        ``"auto"`` (default): the compiled cone paths (:mod:`afvsgp_gym.cbf.binding_cones`)
        for programs with one or several cones when they are built; ``"numpy"``: the numpy
        paths only; ``"compiled"``: require them (``ImportError`` if they were not built); a
        resolved ``Backend``: as it says (the filter's). See :mod:`afvsgp_gym._compiled`.

    Attributes
    ----------
    compiled : bool
        True when the compiled cone paths run.
    """

    def __init__(
        self,
        action_low,
        action_high,
        n_constraints: int | None = None,
        *,
        qp_solver: str | None = None,
        tol: float = 1e-9,
        fallback_regularization: float = 1e-4,
        fast_path: bool = True,
        backend: str | _compiled.Backend = "auto",
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
        if n_constraints is not None and (
            not isinstance(n_constraints, (int, np.integer)) or n_constraints < 0
        ):
            raise ValueError(
                f"n_constraints must be None or an integer >= 0. Got: {n_constraints!r}"
            )
        if qp_solver is not None:
            import qpsolvers

            if qp_solver not in qpsolvers.available_solvers:
                raise ValueError(
                    f"qp_solver {qp_solver!r} is not available; installed: "
                    f"{qpsolvers.available_solvers}"
                )
        if not (np.isfinite(tol) and 0 < tol < 1):
            raise ValueError(f"tol must be in (0, 1). Got: {tol!r}")
        self.low, self.high = low, high
        self.m = low.size
        self.qp_solver = qp_solver
        self.tol = float(tol)
        self.fallback_regularization = float(fallback_regularization)
        self.fast_path = bool(fast_path)
        self.compiled = _compiled.resolve(backend, ("cones",)).cones
        #: largest ``||u||`` in the box: the action scale of :func:`fastpath.constraint_scales`
        self.bound_norm = float(np.linalg.norm(np.maximum(np.abs(low), np.abs(high))))
        #: smallest ``high - low``: coordinates this close (times 1e-12) outside count as in
        self.box_width = float((high - low).min())
        self.programs = ConePrograms(low, high, self.tol, self.fallback_regularization)

    # ------------------------------------------------------------------ public
    def prepare(self, n_constraints: int, cones: bool = True) -> None:
        """Build clarabel's solver objects for 1 to ``n_constraints`` constraints (with cones
        or, ``cones=False``, half-spaces) before the control loop, which then only updates
        them; a solve otherwise builds one on the first program of each size."""
        self.programs.prepare("socp" if cones else "qp", range(1, int(n_constraints) + 1))

    def margins(self, u, a0, a, G=None) -> np.ndarray:
        """``a0 + a @ u - ||G ubar||`` for every constraint."""
        if G is not None and self.compiled and len(a0) > 1:
            out = binding_cones.cone_margins(u, a0, a, G)
            if out is not None:
                return out
        out = np.asarray(a, dtype=np.float64) @ u + np.asarray(a0, dtype=np.float64)
        if G is not None:
            G = np.asarray(G, dtype=np.float64)
            ubar = np.empty(self.m + 1)
            ubar[0] = 1.0
            ubar[1:] = u
            if G.shape[0] == 1:  # one cone: fewer numpy calls
                v = G[0].dot(ubar)
                out -= math.sqrt(float(v.dot(v)))
                return out
            v = G @ ubar
            out -= np.sqrt(np.einsum("ki,ki->k", v, v))
        return out

    def solve(self, u_nom, a0, a, G=None, backup=None) -> SOCPResult:
        """Filter ``u_nom``: the program's solution, or a flagged backup/fallback.

        Never raises for NaN/inf values (they give the flagged fallback, status
        ``"invalid_input"``; a non-finite constraint is left out of it); raises ValueError for
        inputs of the wrong shape.

        Parameters
        ----------
        u_nom : array_like of shape (m,)
        a0 : array_like of shape (k,)
            Action-free part of each constraint (``k >= 0``; ``k = 0`` returns the clipped
            proposal, status ``"inactive"``).
        a : array_like of shape (k, m)
            Action coefficients.
        G : array_like of shape (k, m+1, m+1) or None
            Cone matrices ``beta L'``; None (or all zero) gives the plain QP.
        backup : array_like of shape (m,), zero-argument callable returning one, or None
            Action applied (clipped to the bounds, status ``"backup:..."``) when the program is
            infeasible or fails; the callable is only evaluated then. None, or a backup that
            is not finite, has the wrong shape or raises: the max-worst-margin fallback.
        """
        t0 = time.perf_counter()
        m = self.m
        u_nom = np.asarray(u_nom, dtype=np.float64)
        a0 = np.asarray(a0, dtype=np.float64)
        a = np.asarray(a, dtype=np.float64)
        if u_nom.shape != (m,):
            u_nom = u_nom.ravel()
            if u_nom.shape != (m,):
                raise ValueError(f"u_nom must have shape ({m},). Got: {u_nom.shape}")
        if a0.ndim != 1:
            a0 = a0.ravel()
        k = a0.size
        if a.shape != (k, m):
            if a.size != k * m:
                raise ValueError(
                    f"a must have shape ({k}, {m}) for {k} constraints. Got: {a.shape}"
                )
            a = a.reshape(k, m)
        if G is not None:
            G = np.asarray(G, dtype=np.float64)
            if G.shape != (k, m + 1, m + 1):
                if G.size != k * (m + 1) ** 2:
                    raise ValueError(
                        f"G must have shape ({k}, {m + 1}, {m + 1}) or be None. Got: {G.shape}"
                    )
                G = G.reshape(k, m + 1, m + 1)
            if float(np.vdot(G, G)) == 0.0 and not G.any():  # no cone (NaN: caught below)
                G = None
        uc = fastpath.clip(u_nom, self.low, self.high)
        if G is None:
            marg = a @ uc
            marg += a0
        else:
            marg = self.margins(uc, a0, a, G)
        # any NaN/inf in the data makes a margin (or u_nom's sum) non-finite
        total = float(marg[0]) if k == 1 else float(marg.sum())
        if not math.isfinite(total + sum(u_nom.tolist())):
            return self._invalid(u_nom, a0, a, G, t0, backup)
        if k == 0 or (total if k == 1 else float(marg.min())) >= 0.0:  # the filter is inactive
            return SOCPResult(uc, True, "inactive", marg, time.perf_counter() - t0)
        if G is None and self.fast_path:
            try:
                found = self._fast_qp(u_nom, a0, a, marg)
            except Exception:  # an uncertified case: clarabel decides
                found = None
            if found is not None and isinstance(found[0], str):  # certified by Farkas
                return self._fallback("infeasible", u_nom, uc, a0, a, G, None, t0, backup,
                                      rows=found[1])
            if found is not None:
                u, path, marg = found
                return SOCPResult(u, True, f"certified:{path}", marg, time.perf_counter() - t0)
        tol = fastpath.Tolerance(a0, a, G, self.bound_norm)
        working = None
        if self.fast_path and G is not None:
            try:
                found = self._fast(u_nom, uc, a0, a, G, marg, tol)
            except Exception:  # an uncertified case: clarabel decides
                found = None
            if isinstance(found, np.ndarray):
                working = found
            elif found is not None:
                u, path, marg = found
                return SOCPResult(u, True, f"certified:{path}", marg, time.perf_counter() - t0)
        try:
            if working is not None:
                u, status, marg = self._solve_working_set(u_nom, a0, a, G, tol, working)
            else:
                u, status, marg = self._solve_whole(u_nom, a0, a, G, tol)
            if status in SOLVED:
                return SOCPResult(u, True, status, marg, time.perf_counter() - t0)
        except Exception as exc:  # never raise in the control loop
            status = f"error:{type(exc).__name__}"
        return self._fallback(status, u_nom, uc, a0, a, G, None, t0, backup)

    # ------------------------------------------------------------------ internals
    def _accepted(self, u, a0, a, G, tol):
        """``(u, margins)`` of a solver answer clipped to the box, and the constraints it
        violates beyond ``FEASIBILITY_TOL`` of their scale (empty: accepted)."""
        u = fastpath.clip(u, self.low, self.high)
        marg = self.margins(u, a0, a, G)
        if float(marg.min()) >= 0.0:
            return u, marg, np.zeros(0, dtype=int)
        slack = marg + tol.array() * (FEASIBILITY_TOL / fastpath.FEAS_TOL)
        return u, marg, np.flatnonzero(~(slack >= 0.0))

    def _solve_whole(self, u_nom, a0, a, G, tol):
        """``(u, status, margins)`` of clarabel (or ``qp_solver``) on the whole program;
        status ``"constraint_violated"`` when its answer fails the feasibility check."""
        if G is None and self.qp_solver is not None:
            x, status = self._run_qpsolvers(u_nom, a0, a)
        else:
            x, status = self.programs.solve("qp" if G is None else "socp", u_nom, a0, a, G)
        u = x[: self.m]
        if status not in SOLVED or not math.isfinite(float(u.sum())):
            return u, status, None
        u, marg, bad = self._accepted(u, a0, a, G, tol)
        return u, (status if bad.size == 0 else "constraint_violated"), marg

    def _solve_working_set(self, u_nom, a0, a, G, tol, working):
        """:meth:`_solve_whole` through working sets of cones (module docstring): clarabel on
        the cones ``working``, enlarged by those the answer violates, for at most
        ``WORKING_SET_ROUNDS`` rounds, then on all of them."""
        for _ in range(WORKING_SET_ROUNDS):
            x, status = self.programs.solve("socp", u_nom, a0[working], a[working],
                                            G[working])
            u = x[: self.m]
            if status not in SOLVED or not math.isfinite(float(u.sum())):
                if status.endswith("Infeasible"):  # a relaxation of the program is infeasible
                    return u, status, None
                break
            u, marg, bad = self._accepted(u, a0, a, G, tol)
            if bad.size == 0:
                return u, status, marg
            working = np.union1d(working, _most_violated(bad, marg, tol))
        return self._solve_whole(u_nom, a0, a, G, tol)

    def _farthest_cones(self, uc, a0, a, G, marg) -> np.ndarray:
        """The violated constraints at the clipped proposal ``uc``, farthest first: by the
        distance ``-c_i / ||grad c_i||`` to their linearisation there."""
        violated = np.flatnonzero(marg < 0.0)
        g = G[violated]
        v = g[:, :, 0] + g[:, :, 1:] @ uc
        nv = np.sqrt(np.einsum("ki,ki->k", v, v))
        grad = a[violated] - np.einsum("kji,kj->ki", g[:, :, 1:], v) / np.where(
            nv > 0.0, nv, 1.0)[:, None]
        with np.errstate(divide="ignore"):
            dist = -marg[violated] / np.sqrt(np.einsum("ki,ki->k", grad, grad))
        return violated[np.argsort(-dist, kind="stable")]

    def _halfspace_scales(self, a0, a):
        """``(norms, tol)`` of half-spaces: the row norms ``||a_i||`` (zeros replaced by 1) and
        the feasibility tolerances ``FEAS_TOL scale_i`` (from the true norms)."""
        norms = np.sqrt(np.einsum("ij,ij->i", a, a))
        tol = fastpath.constraint_scales(a0, a, None, self.bound_norm, norms)
        tol *= fastpath.FEAS_TOL
        norms[norms == 0.0] = 1.0
        return norms, tol

    def _fast_qp(self, u_nom, a0, a, marg):
        """``(u, path, margins at u)`` from a certified fast path of the QP (paper eq. 04,
        ``G = None``), ``("infeasible", rows)`` (a Farkas certificate for the half-spaces
        ``rows``, hence for the whole program) or None.

        One violated half-space at the clipped proposal: its projection. Otherwise the
        least-distance program over a working set of half-spaces, starting with those
        violated at the clipped proposal (the others are satisfied there), enlarged by those
        its answer violates, ``QP_WORKING_SET_ROUNDS`` times at most: an answer satisfying
        every constraint is certified against the whole program (its multipliers, zero for
        the others, in :func:`fastpath.certify_halfspaces`), and an infeasible working set
        (a Farkas certificate for its rows) proves the whole program infeasible."""
        low, high = self.low, self.high
        norms, tol = self._halfspace_scales(a0, a)
        work = np.flatnonzero(marg < 0.0)
        if work.size == 1:
            i = int(work[0])
            sol = fastpath.project_halfspace_box(u_nom, float(a0[i]), a[i], low, high)
            if sol is not None:
                u, lam = sol
                c = a @ u
                c += a0
                if fastpath.certify_halfspaces(u, u_nom, c, tol, work, np.array([lam]),
                                               a[work], low, high):
                    return u, "halfspace", c
        for _ in range(QP_WORKING_SET_ROUNDS):
            sol = fastpath.project_polyhedron_box(u_nom, a0[work], a[work], low, high,
                                                  norms[work])
            if sol is None:
                return None
            if isinstance(sol, str):  # "infeasible": for the whole program
                return sol, work
            u, lam = sol
            c = a @ u
            c += a0
            act = np.flatnonzero(lam)
            idx = work[act]
            if fastpath.certify_halfspaces(u, u_nom, c, tol, idx, lam[act], a[idx], low,
                                           high):
                return u, "polyhedron", c
            bad = np.flatnonzero(c + tol < 0.0)
            if bad.size == 0:
                return None  # feasible but not certified
            grown = np.union1d(work, bad)
            if grown.size == work.size:
                return None  # the working set's answer violates its own rows
            work = grown
        return None

    def _fast(self, u_nom, uc, a0, a, G, marg, tol):
        """``(u, path, margins at u)`` from a certified fast path with cones (``G`` not
        None), or the working set of cones for clarabel (an index array), or None."""
        low, high = self.low, self.high
        if a0.size == 1:
            if self.compiled:
                found = self._one_cone_compiled(u_nom, uc, a0, a, G, tol)
                if found is not None:
                    return found
            return self._one_cone(u_nom, float(a0[0]), a[0], G[0], tol)
        # several cones: the compiled path searches the binding cones from the most violated
        # one; else the projection onto the farthest one answers the program when that cone
        # is the only one binding at the optimum, and if it does not, starts the compiled
        # search once more or clarabel's working set
        if self.compiled:
            found = self._binding_cones(u_nom, a0, a, G, tol, None, uc)
            if found is not None:
                return found
        order = self._farthest_cones(uc, a0, a, G, marg)
        i = int(order[0])
        found = self._project_one(u_nom, float(a0[i]), a[i], G[i])
        if found is None:
            return order[:2]
        u, lam, _, grad, path = found
        c = self.margins(u, a0, a, G)
        if fastpath.certify(u, u_nom, c, tol, np.array([i]), np.array([lam]),
                            grad[None], low, high):
            return u, path, c
        violated = np.flatnonzero(c < 0.0)
        if self.compiled and path == "cone":  # once more, from the projection onto cone i
            found = self._binding_cones(u_nom, a0, a, G, tol, i, u, lam)
            if found is not None:
                return found
        return np.union1d([i], _most_violated(violated, c, tol))

    def _binding_cones(self, u_nom, a0, a, G, tol, i: int | None, u, lam: float = 0.0):
        """``(u, path, margins at u)`` from :func:`binding_cones.solve_binding_set` (the
        binding set searched from cone ``i`` with multiplier ``lam`` at the point ``u``; with
        ``i`` None, from the cone most violated at ``u``), certified against the whole
        program; None if it does not settle or certify."""
        low, high = self.low, self.high
        start = np.zeros(a0.size, dtype=bool)
        lam0 = np.zeros(a0.size)
        if i is not None:
            start[i] = True
            lam0[i] = lam
        sol = binding_cones.solve_binding_set(u_nom, a0, a, G, low, high, tol.array(), u,
                                              lam0, start, BINDING_CONES_MAX)
        if sol is None:
            return None
        u, lams, binding = sol
        ok, c = binding_cones.certify_set(u_nom, a0, a, G, low, high, tol.array(), u, lams,
                                          binding, fastpath.DIST_TOL)
        if ok:
            return u, "cone" if int(binding.sum()) == 1 else "cones", c
        return None

    def _project_one(self, u_nom, a0: float, a, G):
        """``(u, lam, c(u), grad c(u), path)``: the projection of ``u_nom`` onto one
        constraint (cone, or half-space when ``G = 0``) and the box; None if it fails or
        ends at the cone's apex."""
        if G.any():
            sol = fastpath.project_cone_box(u_nom, a0, a, G, self.low, self.high)
            path = "cone"
        else:
            sol = fastpath.project_halfspace_box(u_nom, a0, a, self.low, self.high)
            path = "halfspace"
        out = _with_margin(sol, a0, a, G)
        return None if out is None else (*out, path)

    def _one_cone_compiled(self, u_nom, uc, a0, a, G, tol):
        """``(u, "cone", margins at u)`` for a program with one cone from the compiled
        projection (:func:`binding_cones.project_cones_box`, k = 1), certified; or None.

        Newton's method starts at the clipped proposal ``uc`` with no face fixed; if that does
        not settle and certify, at the projection onto the cone linearised at ``uc`` (its
        faces and multiplier, usually those of the answer)."""
        low, high = self.low, self.high
        tol_i = np.array([tol.one(0)])
        sol = binding_cones.project_cones_box(u_nom, a0, a, G, low, high, uc, _ZERO,
                                              np.zeros(self.m, dtype=bool))
        found = self._certified_one(sol, u_nom, a0, a, G, tol_i)
        if found is not None:
            return found
        a0i, ai = float(a0[0]), a[0]
        c, grad = fastpath.cone_margin_gradient(uc, a0i, ai, G[0])
        if grad is None:
            return None
        lin = fastpath.project_halfspace_box(u_nom, c - float(grad.dot(uc)), grad, low, high)
        if lin is None:
            return None
        u, lam = lin
        sol = binding_cones.project_cones_box(u_nom, a0, a, G, low, high, u, [lam],
                                              u != u_nom + lam * grad)
        return self._certified_one(sol, u_nom, a0, a, G, tol_i)

    def _certified_one(self, sol, u_nom, a0, a, G, tol):
        """``(u, "cone", margins at u)`` of an answer ``sol = (u, lam)`` (``lam`` of shape
        (1,)) for the program with the one cone ``a0, a, G`` (shapes (1,), (1, m), (1, m+1,
        m+1)) and its tolerance ``tol`` (1,) when the compiled KKT certificate
        (:func:`binding_cones.certify_set`, the test of :func:`fastpath.certify_one`)
        accepts it; None otherwise (or if ``sol`` is None). ``u`` is clipped to the box first
        (the compiled projection returns it inside unless its multiplier is negative)."""
        if sol is None:
            return None
        u, lam = fastpath.clip(sol[0], self.low, self.high), sol[1]
        found = binding_cones.certify_set(u_nom, a0, a, G, self.low, self.high, tol, u, lam,
                                          _ONE, fastpath.DIST_TOL)
        if found is None or not found[0]:
            return None
        return u, "cone", found[1]

    def _one_cone(self, u_nom, a0: float, a, G, tol):
        """``(u, "cone", margins at u)`` for a program with one (non-zero) cone (paper eq. 05
        with k = 1, the end-effector barrier's case), certified; or None."""
        out = _with_margin(fastpath.project_cone_box(u_nom, a0, a, G, self.low, self.high),
                           a0, a, G)
        if out is None:
            return None
        u, lam, c, grad = out
        if fastpath.certify_one(u, u_nom, c, tol.one(0), lam, grad, self.low, self.high):
            return u, "cone", np.array([c])
        return None

    def _fast_max_margin(self, u_nom, uc, a0, a, rows=None):
        """The max-worst-margin action of the QP (``min -t + eps/2 ||u - u_nom||^2`` s.t.
        ``a0 + a u >= t``, the box), certified by :func:`fastpath.certify_max_margin`, or None.

        A working set of half-spaces (``rows``, else all) is solved by
        :class:`fastpath.MaxMarginLDP` (its active set) and
        :func:`fastpath.polish_max_margin` (the exact optimum on that active set); an answer
        whose worst margin is its own ``t`` (every other half-space satisfied at that margin)
        is the optimum of the whole program, whose feasible set lies inside the working
        set's. Otherwise the working set grows by the half-spaces the answer violates,
        ``QP_WORKING_SET_ROUNDS`` times at most."""
        low, high, eps = self.low, self.high, self.fallback_regularization
        if not eps > 0.0:
            return None
        norms, tol = self._halfspace_scales(a0, a)
        c = a @ uc
        c += a0
        t_ref = float(c.min())
        work = np.arange(a0.size) if rows is None else rows
        ldp = fastpath.MaxMarginLDP(u_nom, a0, a, low, high, eps, norms)
        for _ in range(QP_WORKING_SET_ROUNDS):
            found = ldp.active_set(work, t_ref)
            if found is None:
                return None
            act, lower, upper = found
            sol = fastpath.polish_max_margin(u_nom, a0, a, low, high, eps, act, lower, upper)
            if sol is None:
                return None
            u, t, mu = sol
            out = np.maximum(low - u, u - high)
            if not float(out.max()) <= 1e-12 * self.box_width:  # a free coordinate left it
                return None
            u = fastpath.clip(u, low, high)
            c = a @ u
            c += a0
            if fastpath.certify_max_margin(u, u_nom, c, tol, act, mu, a[act], low, high, eps):
                return u
            bad = np.flatnonzero(c - t + tol < 0.0)
            grown = np.union1d(work, bad)
            if grown.size == work.size:
                return None  # the working set's answer does not certify
            work, t_ref = grown, t
        return None

    def _run_qpsolvers(self, u_nom, a0, a):
        import qpsolvers
        import scipy.sparse as sp

        x = qpsolvers.solve_qp(
            sp.identity(self.m, format="csc"),
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

    def _invalid(self, u_nom, a0, a, G, t0, backup) -> SOCPResult:
        """Non-finite data: invalid constraints become vacuous, a non-finite proposal the box
        centre; then the flagged backup/fallback."""
        valid = np.isfinite(a0) & np.all(np.isfinite(a), axis=1)
        if G is not None:
            valid &= np.all(np.isfinite(G), axis=(1, 2))
            G = np.where(valid[:, None, None], G, 0.0)
            if not G.any():
                G = None
        a0 = np.where(valid, a0, 1.0)
        a = np.where(valid[:, None], a, 0.0)
        if not np.all(np.isfinite(u_nom)):
            u_nom = 0.5 * (self.low + self.high)
        uc = np.clip(u_nom, self.low, self.high)
        return self._fallback("invalid_input", u_nom, uc, a0, a, G, valid, t0, backup)

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

    def _fallback(self, status, u_nom, uc, a0, a, G, valid, t0, backup=None,
                  rows=None) -> SOCPResult:
        """The flagged backup action, or the max-worst-margin action: for half-spaces
        (``G`` None) from :meth:`_fast_max_margin` when it is certified (``rows``: the
        half-spaces of a Farkas certificate, its first working set), else clarabel's."""
        u = self._backup_action(backup)
        if u is not None:
            status = f"backup:{status}"
        elif a0.size == 0:
            u = uc
        else:  # maximise the worst margin within the bounds
            u = uc
            kind = "fallback_qp" if G is None else "fallback_socp"
            try:
                found = None
                if G is None and self.fast_path:
                    try:
                        found = self._fast_max_margin(u_nom, uc, a0, a, rows)
                    except Exception:  # an uncertified case: clarabel decides
                        found = None
                if found is not None:
                    u = found
                else:
                    x, fb_status = self.programs.solve(kind, u_nom, a0, a, G)
                    if fb_status in SOLVED and np.all(np.isfinite(x[: self.m])):
                        u = np.clip(x[: self.m], self.low, self.high)
                status = f"fallback:{status}" if status != "invalid_input" else status
            except Exception as exc:
                status = f"fallback_failed:{type(exc).__name__}"
        marg = self.margins(u, a0, a, G)
        if valid is not None:
            marg = np.where(valid, marg, np.nan)
        return SOCPResult(u, False, status, marg, time.perf_counter() - t0)


def _most_violated(idx: np.ndarray, c: np.ndarray, tol: fastpath.Tolerance) -> np.ndarray:
    """The ``WORKING_SET_ADD`` constraints of ``idx`` most violated relative to their scale
    (margins ``c``), or all of ``idx`` if there are no more."""
    if idx.size <= WORKING_SET_ADD:
        return idx
    return idx[np.argsort(c[idx] / tol.at(idx))[:WORKING_SET_ADD]]


def _with_margin(sol, a0, a, G):
    """``(u, lam, c(u), grad c(u))`` of a one-constraint projection ``sol = (u, lam)`` (the
    constraint's own gradient when it is inactive, ``lam = 0``); None if ``sol`` is None or
    the cone's gradient is undefined at ``u`` (its apex)."""
    if sol is None:
        return None
    u, lam = sol
    c, grad = fastpath.cone_margin_gradient(u, a0, a, G)
    if lam == 0.0:
        grad = a
    elif grad is None:
        return None
    return u, lam, c, grad
