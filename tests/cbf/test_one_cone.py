"""The one-cone path of the filter's cone program (paper eq. 05 with k = 1) on seeded generic
programs (random covariances, condition numbers up to 1e12, the proposal outside the safe set:
afvsgp_gym.benchmarks.solver.generic_programs): the compiled projection's certified answers
against clarabel and a 40-digit reference, the certificate against perturbed answers, and the
numpy and compiled backends against each other.

Tolerances: against the 40-digit reference and across backends, rounding amplified by the
condition number of the KKT matrix at the answer (free coordinates and the multiplier);
against clarabel, the distance its own answer may be from the optimum, from its suboptimality
and constraint violation (the objective is 1-strongly convex)."""

import numpy as np
import pytest
import solver_instances  # benchmarks/solver_instances.py (pytest's pythonpath)

from afvsgp_gym import _compiled
from afvsgp_gym.benchmarks.solver import M, generic_programs
from afvsgp_gym.cbf import SOCPFilter, binding_cones, fastpath
from afvsgp_gym.cbf.socp import FEASIBILITY_TOL

needs_core = pytest.mark.skipif(_compiled.extension("cones") is None,
                                reason="afvsgp_gym.cbf._cones not built")
EPS = np.finfo(np.float64).eps
LOW, HIGH = -np.ones(M), np.ones(M)


def _programs(seed: int, n: int = 12):
    return generic_programs(n, 1, seed=seed)


def _kkt(u, u_nom, a0, a, G):
    """``(lam, cond)`` at ``u`` on the cone's boundary: the multiplier fitted to stationarity
    on the free coordinates and the condition number of the KKT matrix ``[[H_FF, -g_F],
    [g_F', 0]]`` (H the Lagrangian's Hessian, g the cone's gradient)."""
    G = G[0]
    v = G @ np.concatenate([[1.0], u])
    nv = np.linalg.norm(v)
    B = G[:, 1:]
    w = B.T @ v / nv
    g = a[0] - w
    F = np.flatnonzero((u > LOW) & (u < HIGH))
    lam = float((u - u_nom)[F] @ g[F] / (g[F] @ g[F]))
    H = np.eye(M) + lam * (B.T @ B - np.outer(w, w)) / nv
    n = F.size
    K = np.zeros((n + 1, n + 1))
    K[:n, :n] = H[np.ix_(F, F)]
    K[:n, n] = -g[F]
    K[n, :n] = g[F]
    return lam, float(np.linalg.cond(K))


def _feasible(res, a0, a, G, bound_norm):
    scale = fastpath.constraint_scales(a0, a, G, bound_norm)
    return (np.all(res.u >= LOW) and np.all(res.u <= HIGH)
            and np.all(res.margins >= -FEASIBILITY_TOL * scale))


@needs_core
@pytest.mark.parametrize("seed", range(4))
def test_compiled_answers_agree_with_clarabel_and_a_40_digit_reference(seed):
    ours = SOCPFilter(LOW, HIGH, backend="compiled")
    clarabel = SOCPFilter(LOW, HIGH, fast_path=False)
    tight = SOCPFilter(LOW, HIGH, fast_path=False, tol=1e-12)
    compiled_answers, refined = 0, 0
    for u_nom, a0, a, G in _programs(seed):
        res = ours.solve(u_nom, a0, a, G)
        assert res.status == "certified:cone", res.status
        assert _feasible(res, a0, a, G, ours.bound_norm)
        uc = np.clip(u_nom, LOW, HIGH)
        tol = fastpath.Tolerance(a0, a, G, ours.bound_norm)
        compiled_answers += ours._one_cone_compiled(u_nom, uc, a0, a, G, tol) is not None
        lam, cond = _kkt(res.u, u_nom, a0, a, G)
        assert lam > 0.0
        # the 40-digit optimum (Newton's method from clarabel's answer at tol 1e-12)
        ref = solver_instances.refine_kkt_mp(tight.solve(u_nom, a0, a, G).u, u_nom, a0, a, G,
                                             LOW, HIGH)
        if ref is not None:
            refined += 1
            err = np.abs(res.u - ref).max()
            assert err <= 1e3 * cond * EPS * (1.0 + np.abs(ref).max()), (err, cond)
        # clarabel's answer (the filter's tolerance, clipped to the box) is delta outside
        # the cone: u* is within sqrt(2 (f(u_c) - f* + lam delta)) + sqrt(2 lam delta) of it
        cl = clarabel.solve(u_nom, a0, a, G)
        assert cl.status in ("Solved", "AlmostSolved")
        delta = max(0.0, -float(cl.margins[0]))
        gap = 0.5 * np.sum((cl.u - u_nom) ** 2) - 0.5 * np.sum((res.u - u_nom) ** 2)
        bound = np.sqrt(2.0 * max(gap + lam * delta, 0.0)) + np.sqrt(2.0 * lam * delta)
        assert np.linalg.norm(res.u - cl.u) <= bound + 1e-12, (np.linalg.norm(res.u - cl.u),
                                                               bound)
    assert compiled_answers >= 11 and refined >= 10, (compiled_answers, refined)


@needs_core
def test_ill_conditioned_covariances_are_answered_exactly():
    """Covariances of condition 1e10 to 1e12: the compiled path certifies, within the
    rounding of the KKT matrix's conditioning of the 40-digit optimum."""
    ours = SOCPFilter(LOW, HIGH, backend="compiled")
    tight = SOCPFilter(LOW, HIGH, fast_path=False, tol=1e-12)
    found = 0
    for u_nom, a0, a, G in generic_programs(120, 1, seed=7):
        if np.linalg.cond(G[0]) ** 2 < 1e10:
            continue
        found += 1
        uc = np.clip(u_nom, LOW, HIGH)
        tol = fastpath.Tolerance(a0, a, G, ours.bound_norm)
        sol = ours._one_cone_compiled(u_nom, uc, a0, a, G, tol)
        assert sol is not None
        u = sol[0]
        ref = solver_instances.refine_kkt_mp(tight.solve(u_nom, a0, a, G).u, u_nom, a0, a, G,
                                             LOW, HIGH)
        if ref is not None:
            _, cond = _kkt(u, u_nom, a0, a, G)
            assert np.abs(u - ref).max() <= 1e3 * cond * EPS * (1.0 + np.abs(ref).max())
    assert found >= 10


@needs_core
@pytest.mark.parametrize("seed", range(3))
def test_certificate_rejects_perturbed_answers(seed):
    """The compiled projection's answer is certified; the same point moved 1e-7 (along the
    cone's boundary or off it), or the exact point with a multiplier off by 1e-3 of itself,
    is not (the certificate bounds the distance to the optimum by 1e-9): by the filter's
    compiled certificate and by the numpy one alike."""
    rng = np.random.default_rng(seed)
    f = SOCPFilter(LOW, HIGH, backend="compiled")
    checked = 0
    for u_nom, a0, a, G in _programs(100 + seed, 6):
        uc = np.clip(u_nom, LOW, HIGH)
        sol = binding_cones.project_cones_box(u_nom, a0, a, G, LOW, HIGH, uc, [0.0],
                                              np.zeros(M, dtype=bool))
        if sol is None:
            continue
        tol = np.array([fastpath.Tolerance(a0, a, G, f.bound_norm).one(0)])

        def certified(v, lam, u_nom=u_nom, a0=a0, a=a, G=G, tol=tol):
            compiled = f._certified_one((v, lam), u_nom, a0, a, G, tol) is not None
            c, grad = fastpath.cone_margin_gradient(v, float(a0[0]), a[0], G[0])
            reference = fastpath.certify_one(v, u_nom, c, float(tol[0]), float(lam[0]), grad,
                                             LOW, HIGH)
            assert compiled == reference
            return compiled

        u, lam = sol
        assert certified(u, lam)
        checked += 1
        for lam_off in (lam * (1.0 + 1e-3), lam * (1.0 - 1e-3), np.zeros(1), -lam):
            assert not certified(u, lam_off)
        free = (u > LOW) & (u < HIGH)
        _, grad = fastpath.cone_margin_gradient(u, float(a0[0]), a[0], G[0])
        for _ in range(5):
            step = rng.normal(size=M) * free
            along = step - (step @ grad) / (grad @ grad) * grad * free
            for d in (step, along):
                v = np.clip(u + 1e-7 * d / np.linalg.norm(d), LOW, HIGH)
                assert not certified(v, lam)
    assert checked >= 4


@needs_core
def test_second_start_answers_where_the_first_does_not_settle():
    """Programs on which Newton's method from the clipped proposal (no face fixed) does not
    settle or certify: the compiled path's second start (the linearised projection's faces)
    answers them, as the numpy projection does."""
    f = SOCPFilter(LOW, HIGH, backend="compiled")
    found = 0
    for u_nom, a0, a, G in generic_programs(150, 1, seed=11):
        uc = np.clip(u_nom, LOW, HIGH)
        tol = fastpath.Tolerance(a0, a, G, f.bound_norm)
        first = binding_cones.project_cones_box(u_nom, a0, a, G, LOW, HIGH, uc, [0.0],
                                                np.zeros(M, dtype=bool))
        if f._certified_one(first, u_nom, a0, a, G, np.array([tol.one(0)])) is not None:
            continue
        sol = f._one_cone_compiled(u_nom, uc, a0, a, G, tol)
        ref = f._one_cone(u_nom, float(a0[0]), a[0], G[0], tol)
        if sol is None or ref is None:
            continue
        found += 1
        _, cond = _kkt(ref[0], u_nom, a0, a, G)
        assert np.abs(sol[0] - ref[0]).max() <= 1e3 * cond * EPS * (1.0 + np.abs(ref[0]).max())
    assert found >= 2


@needs_core
@pytest.mark.parametrize("seed", range(3))
def test_numpy_and_compiled_backends_agree(seed):
    """Either backend certifies the one-cone programs (the numpy one by its secular root),
    with the same answer to the rounding of the KKT matrix's conditioning."""
    numpy_only = SOCPFilter(LOW, HIGH, backend="numpy")
    compiled = SOCPFilter(LOW, HIGH, backend="compiled")
    assert not numpy_only.compiled and compiled.compiled
    for u_nom, a0, a, G in _programs(200 + seed, 20):
        x, y = numpy_only.solve(u_nom, a0, a, G), compiled.solve(u_nom, a0, a, G)
        assert x.status == y.status == "certified:cone"
        _, cond = _kkt(y.u, u_nom, a0, a, G)
        tol = 1e3 * cond * EPS
        assert np.abs(x.u - y.u).max() <= tol * (1.0 + np.abs(y.u).max())
        scale = fastpath.constraint_scales(a0, a, G, compiled.bound_norm)
        assert np.abs(x.margins - y.margins).max() <= tol * scale[0]
