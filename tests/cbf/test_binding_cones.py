"""The compiled several-cones path (afvsgp_gym.cbf.binding_cones) against independent
references: its KKT system solved again in 50 digits (mpmath), shifted half-spaces against the
exact least-distance projection, whole programs against clarabel at a tight tolerance and
SLSQP, nearly parallel cones; bad input to the compiled core; the filter's choice of path."""

import mpmath
import numpy as np
import pytest
from socp_reference import margins as _margins
from socp_reference import slsqp

from afvsgp_gym import _compiled
from afvsgp_gym.cbf import SOCPFilter, binding_cones, fastpath

needs_core = pytest.mark.skipif(_compiled.extension("cones") is None,
                                reason="afvsgp_gym.cbf._cones not built")


def _program(rng, m, K, spread=3.0):
    """Random cones feasible at some u* in the box, and a proposal far outside them."""
    low, high = -rng.uniform(0.5, 2, m), rng.uniform(0.5, 2, m)
    a = rng.normal(size=(K, m))
    G = rng.normal(scale=0.3, size=(K, m + 1, m + 1))
    u_star = rng.uniform(0.5 * low, 0.5 * high)
    a0 = -(a @ u_star) + np.linalg.norm(G @ np.concatenate([[1.0], u_star]), axis=-1)
    a0 += rng.uniform(0.05, 0.5, K)
    u_nom = spread * rng.uniform(low, high)
    return low, high, u_nom, a0, a, G


def _cones_instances(n, m=7, seed=0):
    """``n`` random programs that the filter answers by the several-cones path."""
    rng = np.random.default_rng(seed)
    found = []
    while len(found) < n:
        low, high, u_nom, a0, a, G = _program(rng, m, int(rng.integers(3, 10)))
        res = SOCPFilter(low, high).solve(u_nom, a0, a, G)
        if res.status == "certified:cones":
            found.append((low, high, u_nom, a0, a, G, res))
    return found


@needs_core
@pytest.mark.parametrize("seed", range(6))
def test_answer_solves_its_kkt_system_in_50_digits(seed):
    """The binding cones and box faces of a certified several-cones answer define a square
    KKT system; Newton's method on it in 50 digits (from the answer) gives the same point, to
    a tolerance from the condition number of the system's Jacobian."""
    low, high, u_nom, a0, a, G, res = _cones_instances(1, seed=100 + seed)[0]
    u = res.u
    scale = np.abs(a0) + np.abs(a) @ np.abs(u) + np.abs(G).sum(axis=(1, 2))
    act = np.flatnonzero(np.abs(res.margins) <= 1e-9 * scale)
    free_mask = (u > low) & (u < high)
    assert act.size >= 2
    free = [int(j) for j in np.flatnonzero(free_mask)]
    mpmath.mp.dps = 50
    mpf = mpmath.mpf
    un = mpmath.matrix([mpf(float(x)) for x in u_nom])
    A0 = [mpf(float(x)) for x in a0[act]]
    A = [mpmath.matrix([mpf(float(x)) for x in a[i]]) for i in act]
    GG = [mpmath.matrix([[mpf(float(x)) for x in row] for row in G[i]]) for i in act]
    m, k = u.size, act.size

    def residual(x):
        uu, lam = x[:m], x[m:]
        ubar = mpmath.matrix([1] + [uu[j] for j in range(m)])
        out = mpmath.matrix(len(free) + k, 1)
        grad_sum = mpmath.matrix(m, 1)
        for i in range(k):
            v = GG[i] * ubar
            nv = mpmath.norm(v)
            w = GG[i][:, 1:].T * v / nv
            grad_sum += lam[i] * (A[i] - w)
            out[len(free) + i] = A0[i] + mpmath.fdot(A[i], uu) - nv
        for p, j in enumerate(free):
            out[p] = uu[j] - un[j] - grad_sum[j]
        return out

    lam0 = np.linalg.lstsq(
        np.array([a[i] - G[i][:, 1:].T @ (G[i] @ np.concatenate([[1.0], u])) /
                  np.linalg.norm(G[i] @ np.concatenate([[1.0], u])) for i in act]).T[free_mask],
        (u - u_nom)[free_mask], rcond=None)[0]
    x = mpmath.matrix([mpf(float(v)) for v in u] + [mpf(float(v)) for v in lam0])
    idx = free + list(range(m, m + k))  # the unknowns: free coordinates, multipliers

    def jac(x):
        h = mpf(10) ** -30
        J = mpmath.matrix(len(idx), len(idx))
        r0 = residual(x)
        for c, j in enumerate(idx):
            xp = x.copy()
            xp[j] += h
            d = (residual(xp) - r0) / h
            for r in range(len(idx)):
                J[r, c] = d[r]
        return J

    for _ in range(8):
        J = jac(x)
        step = mpmath.lu_solve(J, residual(x))
        for c, j in enumerate(idx):
            x[j] -= step[c]
    assert mpmath.norm(residual(x)) < mpf(10) ** -40
    u_mp = np.array([float(x[j]) for j in range(m)])
    cond = np.linalg.cond(np.array(jac(x).tolist(), dtype=float))
    tol = 10 * cond * np.finfo(float).eps * (1 + np.abs(u).max())
    np.testing.assert_allclose(u, u_mp, rtol=0, atol=tol)


@needs_core
@pytest.mark.parametrize("k", [2, 3, 4])
def test_cones_with_constant_norms_are_shifted_halfspaces(k):
    """Cones whose G has only its first column are the half-spaces a0 - ||g0|| + a u >= 0:
    where all k bind at the exact least-distance projection (fastpath.project_polyhedron_box,
    an NNLS), the several-cones answer is that projection to rounding whenever it settles
    with multipliers >= 0 (it may decline: the filter then takes the numpy paths), and it
    settles on most of them."""
    rng = np.random.default_rng(k)
    m = 7
    low, high = -np.ones(m), np.ones(m)
    answered = declined = 0
    for _ in range(300):
        a = rng.normal(size=(k, m))
        G = np.zeros((k, m + 1, m + 1))
        G[:, :, 0] = rng.normal(scale=0.3, size=(k, m + 1))
        b = -rng.uniform(0.2, 1.0, k)
        a0 = b + np.linalg.norm(G[:, :, 0], axis=1)
        u_nom = rng.uniform(-1.2, 1.2, m)
        ref = fastpath.project_polyhedron_box(u_nom, b, a, low, high, np.linalg.norm(a, axis=1))
        if ref is None or isinstance(ref, str) or np.count_nonzero(ref[1]) != k:
            continue  # not every half-space binds
        u0 = np.clip(u_nom, low, high)
        sol = binding_cones.project_cones_box(u_nom, a0, a, G, low, high, u0, np.zeros(k),
                                              (u0 <= low) | (u0 >= high))
        if sol is None or sol[1].min() < 0:
            declined += 1
            continue
        np.testing.assert_allclose(sol[0], ref[0], atol=1e-12)
        np.testing.assert_allclose(sol[1], ref[1], rtol=1e-9)
        answered += 1
    assert answered >= 20 and answered > declined


@needs_core
@pytest.mark.parametrize("seed", range(8))
def test_whole_programs_match_clarabel_and_slsqp(seed):
    """Certified several-cones answers are no worse than clarabel's at tol 1e-12 (feasible,
    so within sqrt(2 (f(ref) - f(u*))) of the optimum) nor than SLSQP's."""
    for low, high, u_nom, a0, a, G, res in _cones_instances(3, seed=seed):
        ref = SOCPFilter(low, high, fast_path=False, tol=1e-12).solve(u_nom, a0, a, G)
        assert ref.feasible
        f_ours, f_ref = (0.5 * np.sum((u - u_nom) ** 2) for u in (res.u, ref.u))
        slack = _objective_slack(res, u_nom)
        assert f_ours <= f_ref + slack
        # clarabel's answer is feasible: within sqrt(2 (f(ref) - f(u*))) of u*, and ours
        # within DIST_TOL (1 + max|u|) of it
        bound = np.sqrt(2 * max(f_ref - f_ours + slack, 0.0))
        dist = fastpath.DIST_TOL * (1 + 2 * np.abs(res.u).max())
        assert np.linalg.norm(res.u - ref.u) <= bound + dist
        scale = np.abs(a0) + np.abs(a) @ np.abs(res.u) + np.abs(G).sum(axis=(1, 2))
        assert np.all(_margins(res.u, a0, a, G) >= -1e-12 * scale)
        x = slsqp(u_nom, a0, a, G, low, high)
        if x is not None:
            assert f_ours <= x.fun + slack


def _objective_slack(res, u_nom):
    """How far above the optimum the filter's answer may be: for a certified answer (within
    ``DIST_TOL (1 + max|u|)`` of the optimum u*) ``|u - u_nom| d + d^2 / 2``, for clarabel's
    (tol 1e-9) ten times its gap tolerance."""
    if res.status.startswith("certified"):
        d = fastpath.DIST_TOL * (1 + np.abs(res.u).max())
        return np.linalg.norm(res.u - u_nom) * d + d * d / 2
    return 1e-8 * (1 + 0.5 * np.sum((res.u - u_nom) ** 2))


@needs_core
@pytest.mark.parametrize("angle", [1e-3, 1e-6, 1e-9])
def test_nearly_parallel_cones_give_the_programs_optimum(angle):
    """Two cones that differ by a small rotation of a (an ill-conditioned Schur complement):
    whatever path answers, the answer is feasible and optimal to that path's accuracy
    against clarabel at tol 1e-12."""
    rng = np.random.default_rng(3)
    m = 7
    low, high = -2 * np.ones(m), 2 * np.ones(m)
    for _ in range(10):
        a1 = rng.normal(size=m)
        d = rng.normal(size=m)
        d -= d @ a1 / (a1 @ a1) * a1
        a2 = a1 + angle * np.linalg.norm(a1) * d / np.linalg.norm(d)
        G = rng.normal(scale=0.2, size=(1, m + 1, m + 1)).repeat(2, axis=0)
        a = np.stack([a1, a2])
        a0 = np.array([-0.3, -0.3]) + np.linalg.norm(G[:, :, 0], axis=1)
        u_nom = rng.uniform(-1.5, 1.5, m)
        res = SOCPFilter(low, high).solve(u_nom, a0, a, G)
        ref = SOCPFilter(low, high, fast_path=False, tol=1e-12).solve(u_nom, a0, a, G)
        assert res.feasible == ref.feasible
        if not ref.feasible:
            continue
        f_ours, f_ref = (0.5 * np.sum((u - u_nom) ** 2) for u in (res.u, ref.u))
        assert f_ours <= f_ref + _objective_slack(res, u_nom)
        scale = np.abs(a0) + np.abs(a) @ np.abs(res.u) + np.abs(G).sum(axis=(1, 2))
        assert np.all(_margins(res.u, a0, a, G) >= -1e-8 * scale)


@needs_core
def test_compiled_and_numpy_paths_give_the_same_optimum():
    """The backend "numpy" takes the numpy paths (clarabel on working sets): the same optimum
    to clarabel's accuracy, and the compiled path certifies programs the numpy one cannot."""
    taken = 0
    for low, high, u_nom, a0, a, G, res in _cones_instances(10, seed=50):
        off = SOCPFilter(low, high, backend="numpy").solve(u_nom, a0, a, G)
        assert off.status != "certified:cones"
        np.testing.assert_allclose(res.u, off.u, atol=1e-4)
        taken += off.status in ("Solved", "AlmostSolved")
    assert taken >= 5


@needs_core
def test_bad_input_to_the_compiled_core_is_refused():
    m, k = 7, 2
    args = dict(u_nom=np.zeros(m), a0=np.ones(k), a=np.ones((k, m)),
                G=np.ones((k, m + 1, m + 1)), low=-np.ones(m), high=np.ones(m), u=np.zeros(m),
                lam=np.zeros(k), fixed=np.zeros(m, dtype=bool))
    from afvsgp_gym.cbf import _cones

    for name, bad in [("a", np.ones((k, m + 1))), ("G", np.ones((k, m, m))),
                      ("lam", np.zeros(k + 1)), ("fixed", np.zeros(m))]:
        with pytest.raises(ValueError, match=name):
            _cones.project(*{**args, name: bad}.values())
    with pytest.raises(ValueError, match="u_nom"):
        _cones.project(*{**args, "u_nom": np.zeros(17)}.values())
    with pytest.raises((BufferError, TypeError, ValueError)):  # a read-only answer buffer
        u = np.zeros(m)
        u.flags.writeable = False
        _cones.project(*{**args, "u": u}.values())
    solve = dict(args, tol=np.ones(k), binding=np.zeros(k, dtype=bool))
    order = ["u_nom", "a0", "a", "G", "low", "high", "tol", "u", "lam", "binding"]
    for name, bad in [("tol", np.ones(k + 1)), ("binding", np.zeros(k))]:
        with pytest.raises(ValueError, match=name):
            _cones.solve(*[{**solve, name: bad}[n] for n in order], 2)
    with pytest.raises(ValueError, match="max_binding"):
        _cones.solve(*[solve[n] for n in order], binding_cones.MAX_CONES + 1)
    # NaN data end in a failure code, not a loop or an answer
    nan_g = args["G"].copy()
    nan_g[0, 0, 0] = np.nan
    assert _cones.solve(*[{**solve, "G": nan_g}[n] for n in order], 2) != 0
    # too many cones for the core: the wrapper declines (the filter takes the numpy paths)
    K = binding_cones.MAX_CONES + 1
    assert binding_cones.project_cones_box(np.zeros(m), np.ones(K), np.ones((K, m)),
                                           np.ones((K, m + 1, m + 1)), -np.ones(m),
                                           np.ones(m), np.zeros(m), np.zeros(K),
                                           np.zeros(m, dtype=bool)) is None


def test_backend_compiled_without_the_core_is_an_import_error(without_extensions):
    without_extensions("cones")
    with pytest.raises(ImportError, match=r"backend='compiled' needs afvsgp_gym\.cbf\._cones"):
        SOCPFilter(-np.ones(2), np.ones(2), backend="compiled")
    assert not SOCPFilter(-np.ones(2), np.ones(2)).compiled
    with pytest.raises(ValueError, match="backend must be one of"):
        SOCPFilter(-np.ones(2), np.ones(2), backend="no")


class _FixedTol:
    """fastpath.Tolerance with given values."""

    def __init__(self, tol):
        self.tol = tol

    def at(self, idx):
        return self.tol[idx]


def _python_certificate(u, u_nom, a0, a, G, low, high, tol, lam, binding) -> bool:
    """fastpath.certify with the gradients of fastpath.cone_margin_gradient (numpy)."""
    rows = np.flatnonzero(binding)
    grads = [fastpath.cone_margin_gradient(u, float(a0[j]), a[j], G[j])[1] for j in rows]
    if any(g is None for g in grads):
        return False
    return bool(fastpath.certify(u, u_nom, _margins(u, a0, a, G), _FixedTol(tol), rows,
                                 lam[rows], np.array(grads), low, high))


@needs_core
def test_compiled_certificate_decides_as_the_numpy_one(monkeypatch):
    """binding_cones.certify_set (the certificate in C) against fastpath.certify with numpy
    gradients: the same decision on the binding-set answers the filter found, on answers moved
    off the optimum by 1e-6 (not certified), with a multiplier negated, and at NaN; its
    margins equal the reference formula's to the rounding of c_q (a few eps times the terms'
    size)."""
    eps = np.finfo(float).eps
    found = []
    solve = binding_cones.solve_binding_set

    def recording(*args):
        sol = solve(*args)
        if sol is not None:
            found.append((args, sol))
        return sol

    monkeypatch.setattr(binding_cones, "solve_binding_set", recording)
    _cones_instances(8, seed=7)
    assert len(found) >= 8
    checked = certified = 0
    for (u_nom, a0, a, G, low, high, tol, *_), (u, lam, binding) in found:
        moved = np.clip(u + 1e-6 * np.sign(u_nom - u), low, high)
        neg = lam.copy()
        neg[np.flatnonzero(binding)[0]] *= -1.0
        nan_u = u.copy()
        nan_u[0] = np.nan
        for point, mult in [(u, lam), (moved, lam), (u, neg), (nan_u, lam)]:
            ok, c = binding_cones.certify_set(u_nom, a0, a, G, low, high, tol, point, mult,
                                              binding, fastpath.DIST_TOL)
            if point is u and mult is lam:
                certified += ok
            else:
                assert not ok
            if np.isfinite(point).all():
                assert ok == _python_certificate(point, u_nom, a0, a, G, low, high, tol,
                                                 mult, binding)
            ref = _margins(point, a0, a, G)
            size = np.abs(a0) + np.abs(a) @ np.abs(point) + np.abs(G).sum(axis=(1, 2)) * (
                1.0 + np.abs(point).max())
            if np.isfinite(point).all():
                assert np.all(np.abs(c - ref) <= 20 * (a.shape[1] + 1) * eps * size)
            else:
                assert np.isnan(c).all()
            checked += 1
    assert checked == 4 * len(found)
    assert certified >= 8  # the filter's certified answers among them


@needs_core
def test_compiled_margins_match_the_reference_formula():
    """binding_cones.cone_margins and SOCPFilter.margins (which uses it for several cones)
    against the reference margins, to the rounding of the terms, at a point near a cone's
    apex (||G ubar|| ~ 1e-12) too."""
    rng = np.random.default_rng(3)
    eps = np.finfo(float).eps
    m, K = 7, 9
    low, high = -np.ones(m), np.ones(m)
    filt = SOCPFilter(low, high)
    for scale in (1.0, 1e-12):
        a0, a = rng.normal(size=K), rng.normal(size=(K, m))
        G = scale * rng.normal(size=(K, m + 1, m + 1))
        u = rng.uniform(low, high)
        ref = _margins(u, a0, a, G)
        size = np.abs(a0) + np.abs(a) @ np.abs(u) + np.abs(G).sum(axis=(1, 2)) * 2.0
        for got in (binding_cones.cone_margins(u, a0, a, G), filt.margins(u, a0, a, G)):
            assert np.all(np.abs(got - ref) <= 20 * (m + 1) * eps * size)


@needs_core
def test_bad_input_to_the_compiled_certificate_is_refused():
    from afvsgp_gym.cbf import _cones

    m, k = 7, 3
    args = dict(u_nom=np.zeros(m), a0=np.ones(k), a=np.ones((k, m)),
                G=np.ones((k, m + 1, m + 1)), low=-np.ones(m), high=np.ones(m),
                tol=np.ones(k), u=np.zeros(m), lam=np.zeros(k),
                binding=np.zeros(k, dtype=bool), margins=np.zeros(k))
    for name, bad in [("G", np.ones((k, m, m))), ("lam", np.zeros(k + 1)),
                      ("binding", np.zeros(k)), ("margins", np.zeros(k, dtype=np.float32))]:
        with pytest.raises(ValueError, match=name):
            _cones.certify(*{**args, name: bad}.values(), 1e-9)
    with pytest.raises(ValueError, match="a0"):
        _cones.margins(np.zeros(m), np.ones((0,)), np.ones((0, m)),
                       np.ones((0, m + 1, m + 1)), np.zeros(0))
