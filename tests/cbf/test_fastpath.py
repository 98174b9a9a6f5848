"""Certified fast paths of the filter against independent references: a 50-digit bisection
(mpmath) for the half-space, the closed-form projection onto the Lorentz cone, SLSQP and
clarabel at a tight tolerance, at degenerate points (box faces active, a root at a breakpoint,
nearly parallel or duplicated constraints, extreme scales, singular G); and the soundness of
the KKT certificate (a point farther than its bound from the optimum is never accepted)."""

import mpmath
import numpy as np
import pytest
from scipy.optimize import minimize

from afvsgp_gym.cbf import SOCPFilter, fastpath


def _tol(a0, a, G=None, bound_norm=10.0):
    return fastpath.Tolerance(np.atleast_1d(a0), np.atleast_2d(a), G, bound_norm)


def _halfspace_mp(u_nom, a0, a, low, high):
    """Projection onto {a0 + a u >= 0} ∩ box by bisection on the multiplier in 50 digits."""
    mpmath.mp.dps = 50
    un = [mpmath.mpf(float(x)) for x in u_nom]
    av = [mpmath.mpf(float(x)) for x in a]
    lo = [mpmath.mpf(float(x)) for x in low]
    hi = [mpmath.mpf(float(x)) for x in high]

    def u_of(lam):
        return [min(max(x + lam * aj, lj), hj)
                for x, aj, lj, hj in zip(un, av, lo, hi, strict=True)]

    def phi(lam):
        return mpmath.mpf(float(a0)) + sum(aj * uj for aj, uj in zip(av, u_of(lam), strict=True))

    if phi(0) >= 0:
        return np.array([float(x) for x in u_of(0)])
    lo_l, hi_l = mpmath.mpf(0), mpmath.mpf(1)
    while phi(hi_l) < 0:
        hi_l *= 2
    for _ in range(200):
        mid = (lo_l + hi_l) / 2
        lo_l, hi_l = (mid, hi_l) if phi(mid) < 0 else (lo_l, mid)
    return np.array([float(x) for x in u_of(hi_l)])


@pytest.mark.parametrize("seed", range(40))
def test_halfspace_box_matches_50_digit_bisection(seed):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(1, 9))
    low, high = -rng.uniform(0.1, 2, m), rng.uniform(0.1, 2, m)
    a = rng.normal(size=m) * (rng.uniform(size=m) > 0.2)  # some zero coefficients
    u_nom = rng.uniform(3 * low, 3 * high)  # often outside the box
    best = float(np.maximum(a * low, a * high).sum())  # max of a u over the box
    at_clip = float(a @ np.clip(u_nom, low, high))
    gap = best - at_clip
    if gap > 0.0:  # the half-space cuts the clipped proposal off, the box's best point not
        a0 = -at_clip - rng.uniform(0.01, 0.99) * gap
    else:  # the clipped proposal is the box's best point: a half-space it satisfies
        a0 = -at_clip + rng.uniform(0.01, 1.0)
    sol = fastpath.project_halfspace_box(u_nom, a0, a, low, high)
    ref = _halfspace_mp(u_nom, a0, a, low, high)
    assert sol is not None
    u, lam = sol
    np.testing.assert_allclose(u, ref, atol=1e-13 * (1 + np.abs(ref).max()))
    assert lam >= 0 and np.all(u >= low) and np.all(u <= high)
    if gap <= 0.0:
        assert lam == 0.0
        np.testing.assert_array_equal(u, np.clip(u_nom, low, high))


def test_halfspace_root_at_a_breakpoint_and_all_faces():
    low, high = -np.ones(3), np.ones(3)
    a = np.array([1.0, 2.0, -1.0])
    # a u = 4 is reached exactly when every coordinate sits at its face: the box corner
    u, lam = fastpath.project_halfspace_box(np.zeros(3), -4.0, a, low, high)
    np.testing.assert_array_equal(u, [1.0, 1.0, -1.0])
    assert lam >= 1.0  # (at least the largest breakpoint, 1 / min|a_j|)
    assert fastpath.project_halfspace_box(np.zeros(3), -4.0 - 1e-9, a, low, high) is None
    # root exactly at the breakpoint where coordinate 2 reaches its face (lam = 0.5)
    u, lam = fastpath.project_halfspace_box(np.zeros(3), -3.0, a, low, high)
    np.testing.assert_allclose(u, [0.5, 1.0, -0.5], rtol=1e-15)
    assert lam == pytest.approx(0.5, rel=1e-15)


@pytest.mark.parametrize("scale", [1e-8, 1e-3, 1.0, 1e3, 1e8])
def test_scaled_constraints_give_the_same_action(scale):
    """(a0, a, G) and c (a0, a, G), c > 0, define the same set: the same action, certified."""
    rng = np.random.default_rng(3)
    m, k = 7, 5
    low, high = -np.ones(m), np.ones(m)
    u_nom = rng.uniform(-1.5, 1.5, m)
    a = rng.normal(size=(k, m))
    a0 = -(a @ np.clip(u_nom, low, high)) + np.array([-0.5, 0.3, 0.4, 2.0, 1.0])
    G = np.zeros((k, m + 1, m + 1))
    G[0] = np.triu(0.05 * rng.normal(size=(m + 1, m + 1)))
    base = SOCPFilter(low, high).solve(u_nom, a0, a, None)
    scaled = SOCPFilter(low, high).solve(u_nom, scale * a0, scale * a, None)
    assert base.status.startswith("certified") and scaled.status.startswith("certified")
    np.testing.assert_allclose(scaled.u, base.u, atol=1e-12)
    base = SOCPFilter(low, high).solve(u_nom, a0, a, G)
    scaled = SOCPFilter(low, high).solve(u_nom, scale * a0, scale * a, scale * G)
    assert scaled.status == base.status == "certified:cone"
    np.testing.assert_allclose(scaled.u, base.u, atol=1e-10)


def _slsqp(u_nom, a0, a, G, low, high):
    def marg(u):
        out = a0 + a @ u
        if G is not None:
            out = out - np.linalg.norm(G[:, :, 1:] @ u + G[:, :, 0], axis=1)
        return out

    r = minimize(lambda u: 0.5 * np.sum((u - u_nom) ** 2), np.clip(u_nom, low, high),
                 jac=lambda u: u - u_nom, bounds=list(zip(low, high, strict=True)),
                 constraints=[{"type": "ineq", "fun": marg}], method="SLSQP",
                 options={"ftol": 1e-15, "maxiter": 1000})
    return r.x


@pytest.mark.parametrize("case", ["parallel", "duplicate", "many", "faces"])
def test_polyhedron_degenerate_cases(case):
    rng = np.random.default_rng(11)
    m = 7
    low, high = -np.ones(m), np.ones(m)
    u_nom = rng.uniform(-0.5, 0.5, m)
    a1 = rng.normal(size=m)
    if case == "parallel":  # two nearly parallel active half-spaces
        a = np.stack([a1, a1 + 1e-9 * rng.normal(size=m), rng.normal(size=m)])
        a0 = -(a @ u_nom) + np.array([-1.0, -1.0, 5.0])
    elif case == "duplicate":  # the same half-space three times (multipliers not unique)
        a = np.stack([a1, a1, a1])
        a0 = -(a @ u_nom) - 1.0
    elif case == "many":  # 100 half-spaces, a few violated, all satisfied at u_star
        a = rng.normal(size=(100, m))
        u_star = rng.uniform(-0.3, 0.3, m)
        a0 = -(a @ u_star) + rng.uniform(0.0, 0.3, 100)
    else:  # u_nom far outside the box: several faces active at the optimum
        u_nom = 3.0 * rng.choice([-1.0, 1.0], m)
        a = rng.normal(size=(2, m))
        a0 = -(a @ np.clip(u_nom, low, high)) - np.array([0.5, 0.2])
    sol = fastpath.project_polyhedron_box(u_nom, a0, a, low, high)
    assert sol is not None
    u, lam = sol
    act = np.flatnonzero(lam)
    c = a @ u + a0
    assert fastpath.certify(u, u_nom, c, _tol(a0, a), act, lam[act], a[act], low, high)
    ref = SOCPFilter(low, high, fast_path=False, tol=1e-12).solve(u_nom, a0, a)
    np.testing.assert_allclose(u, ref.u, atol=1e-6)
    x = _slsqp(u_nom, a0, a, None, low, high)
    if (a0 + a @ x).min() >= -1e-12:  # SLSQP can stop outside the feasible set (1e-8 seen)
        assert 0.5 * np.sum((u - u_nom) ** 2) <= 0.5 * np.sum((x - u_nom) ** 2) + 1e-10


@pytest.mark.parametrize("seed", range(20))
def test_cone_projection_equals_lorentz_closed_form(seed):
    """Constraint u_1 >= ||(u_2, ..., u_m)|| (a = e_1, G picks u_2..u_m) in a box too large
    to matter: the projection onto the second-order cone has the closed form
    ((s + |x|) / 2) (1, x / |x|) for a point (s, x) with |x| > |s|."""
    rng = np.random.default_rng(seed)
    m = int(rng.integers(2, 8))
    low, high = -100 * np.ones(m), 100 * np.ones(m)
    a = np.zeros(m)
    a[0] = 1.0
    G = np.zeros((m + 1, m + 1))
    G[np.arange(1, m), np.arange(2, m + 1)] = 1.0  # G ubar = (0, u_2, ..., u_m, 0)
    x = rng.normal(size=m - 1)
    s = rng.uniform(-0.9, 0.9) * np.linalg.norm(x)
    u_nom = np.concatenate([[s], x])
    nx = np.linalg.norm(x)
    want = 0.5 * (s + nx) * np.concatenate([[1.0], x / nx])
    u, lam = fastpath.project_cone_box(u_nom, 0.0, a, G, low, high)
    np.testing.assert_allclose(u, want, atol=1e-12 * (1 + np.abs(want).max()))
    # lam = |u - u_nom| / |grad c| with grad c = (1, -x / |x|)
    assert lam == pytest.approx(0.5 * (nx - s), rel=1e-9)


def test_cone_with_constant_norm_is_a_shifted_halfspace():
    """G with only its first column: ||G ubar|| = ||g0|| is constant, the cone is the
    half-space a0 - ||g0|| + a u >= 0 (a singular G)."""
    rng = np.random.default_rng(5)
    m = 7
    low, high = -np.ones(m), np.ones(m)
    for _ in range(20):
        u_nom = rng.uniform(-1.5, 1.5, m)
        a = rng.normal(size=m)
        G = np.zeros((m + 1, m + 1))
        G[:, 0] = 0.3 * rng.normal(size=m + 1)
        a0 = -float(a @ np.clip(u_nom, low, high)) - rng.uniform(0.1, 1.0)
        sol = fastpath.project_cone_box(u_nom, a0 + np.linalg.norm(G[:, 0]), a, G, low, high)
        ref = fastpath.project_halfspace_box(u_nom, a0, a, low, high)
        if ref is None:
            continue
        assert sol is not None
        np.testing.assert_allclose(sol[0], ref[0], atol=1e-12)


@pytest.mark.parametrize("rank", [1, 3, 8])
@pytest.mark.parametrize("seed", range(6))
def test_cone_box_against_slsqp_and_clarabel(seed, rank):
    """Random cones (G of rank 1, 3 or full) with the box active in places: the certified
    answer equals clarabel's at tol 1e-12 and is no worse than SLSQP's."""
    rng = np.random.default_rng(seed)
    m = 7
    low, high = -np.ones(m), np.ones(m)
    for _ in range(10):
        u_nom = rng.uniform(-1.6, 1.6, m)
        a = rng.normal(size=(1, m))
        G = (0.3 * rng.normal(size=(m + 1, rank)) @ rng.normal(size=(rank, m + 1)))[None]
        uc = np.clip(u_nom, low, high)
        base = float(a[0] @ uc) - np.linalg.norm(G[0, :, 1:] @ uc + G[0, :, 0])
        a0 = np.array([-base - rng.uniform(0.1, 1.0)])
        res = SOCPFilter(low, high).solve(u_nom, a0, a, G)
        ref = SOCPFilter(low, high, fast_path=False, tol=1e-12).solve(u_nom, a0, a, G)
        if not ref.feasible or float(a0[0] + a[0] @ ref.u) < 1e-6:
            continue  # infeasible, or the optimum at the cone's apex (left to clarabel)
        assert res.status == "certified:cone", res.status
        # clarabel's answer is feasible, so by strong convexity its distance to the optimum
        # is at most sqrt(2 (f(ref) - f(u*))); ours is certified within 1e-9 of u*
        f_ours, f_ref = (0.5 * np.sum((u - u_nom) ** 2) for u in (res.u, ref.u))
        assert f_ours <= f_ref + 1e-12
        assert np.linalg.norm(res.u - ref.u) <= np.sqrt(2 * max(f_ref - f_ours, 0.0)) + 1e-8
        x = _slsqp(u_nom, a0, a, G, low, high)
        xm = a0 + a @ x - np.linalg.norm(G[:, :, 1:] @ x + G[:, :, 0], axis=1)
        if xm.min() >= 0:
            assert 0.5 * np.sum((res.u - u_nom) ** 2) <= 0.5 * np.sum((x - u_nom) ** 2) + 1e-12


@pytest.mark.parametrize("seed", range(10))
def test_certificate_rejects_points_away_from_the_optimum(seed):
    """Soundness: the certified bound is an upper bound on the distance to the optimum, so
    a point 1e-7 away from the exact projection is rejected whatever the multiplier."""
    rng = np.random.default_rng(seed)
    m = 7
    low, high = -np.ones(m), np.ones(m)
    u_nom = rng.uniform(-1.2, 1.2, m)
    a = rng.normal(size=m)
    a0 = -float(a @ np.clip(u_nom, low, high)) - 0.5
    u, lam = fastpath.project_halfspace_box(u_nom, a0, a, low, high)
    tol = _tol(a0, a)
    idx = np.array([0])
    c = np.array([a0 + a @ u])
    assert fastpath.certify(u, u_nom, c, tol, idx, np.array([lam]), a[None], low, high)
    for _ in range(20):
        v = (u + 1e-7 * rng.normal(size=m)).clip(low, high)
        if np.abs(v - u).max() < 1e-8:
            continue
        cv = np.array([a0 + a @ v])
        for mult in (lam, lam * (1 + 1e-3), 0.0, 2 * lam):
            assert not fastpath.certify(v, u_nom, cv, tol, idx, np.array([mult]), a[None],
                                        low, high)
    # a negative multiplier or a violated constraint is never certified
    assert not fastpath.certify(u, u_nom, c, tol, idx, np.array([-lam]), a[None], low, high)
    assert not fastpath.certify(u, u_nom, c - 1e-6, tol, idx, np.array([lam]), a[None],
                                low, high)


def test_nnls_routine_equals_scipys_public_nnls():
    """The non-negative least squares used by the polyhedron path (scipy's compiled routine
    without its wrapper, when available) gives scipy.optimize.nnls's answers."""
    from scipy.optimize import nnls

    rng = np.random.default_rng(0)
    for _ in range(200):
        A = rng.normal(size=(8, int(rng.integers(1, 120))))
        b = rng.normal(size=8)
        np.testing.assert_allclose(fastpath._nnls(A, b, 10 * A.shape[1]), nnls(A, b)[0],
                                   rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", range(20))
def test_certify_halfspaces_is_certify(seed):
    """The half-space certificate with every tolerance given is the general one's test: the
    same verdict on the optimum and on perturbed points and multipliers."""
    rng = np.random.default_rng(1300 + seed)
    m, k = 7, int(rng.integers(2, 40))
    low, high = -np.ones(m), np.ones(m)
    a = rng.normal(size=(k, m))
    a0 = -(a @ rng.uniform(-0.5, 0.5, m)) + rng.uniform(0.0, 0.5, k)
    u_nom = rng.uniform(-2.0, 2.0, m)
    sol = fastpath.project_polyhedron_box(u_nom, a0, a, low, high)
    if sol is None or isinstance(sol, str):
        return
    u, lam = sol
    tol = _tol(a0, a, None, np.sqrt(m))
    tol_arr = fastpath.FEAS_TOL * fastpath.constraint_scales(a0, a, None, np.sqrt(m))
    act = np.flatnonzero(lam)
    for du, dl in [(0.0, 0.0), (1e-6, 0.0), (0.0, 1e-6), (1e-12, 0.0), (0.0, -2.0)]:
        v = np.clip(u + du * rng.normal(size=m), low, high)
        mult = lam[act] * (1.0 + dl) if dl > -1 else -lam[act]
        c = a @ v + a0
        assert fastpath.certify_halfspaces(v, u_nom, c, tol_arr, act, mult, a[act], low,
                                           high) == fastpath.certify(v, u_nom, c, tol, act,
                                                                     mult, a[act], low, high)
    c = a @ u + a0
    assert fastpath.certify_halfspaces(u, u_nom, c, tol_arr, act, lam[act], a[act], low, high)
