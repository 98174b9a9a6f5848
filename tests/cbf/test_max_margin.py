"""The QP's max-worst-margin fallback without clarabel (``SOCPFilter._fast_max_margin``):
its action is the optimum of ``min -t + eps/2 ||u - u_nom||^2 s.t. a0 + a u >= t, box``, checked
against clarabel at a tight tolerance; the certificate rejects perturbed answers; whatever it
cannot certify goes to clarabel."""

import numpy as np
import pytest

from afvsgp_gym.benchmarks.solver import M, make_instances
from afvsgp_gym.cbf import SOCPFilter, fastpath, socp

EPS = 1e-4  # SOCPFilter's default fallback_regularization


def _objective(u, u_nom, a0, a):
    return -float(np.min(a0 + a @ u)) + 0.5 * EPS * float(np.sum((u - u_nom) ** 2))


def _check_against_clarabel(res, u_nom, a0, a, low, high):
    """``res`` (our flagged fallback) against clarabel's max-worst-margin answer at tol
    1e-11: our objective is not above clarabel's, and the actions differ by no more than the
    objective gap allows (the objective is eps-strongly convex: ``eps/2 ||u - u*||^2 <=
    F(u) - F*``, so for our optimum ``||u_cl - u|| <= sqrt(2 (F(u_cl) - F(u)) / eps)``, the gap
    widened by the rounding of ``F``); the worst margins ``t`` then differ by at most
    ``max ||a_i||`` times that."""
    ref = SOCPFilter(low, high, fast_path=False, tol=1e-11).solve(u_nom, a0, a)
    assert not ref.feasible and ref.status.startswith("fallback:")
    f_ours, f_ref = _objective(res.u, u_nom, a0, a), _objective(ref.u, u_nom, a0, a)
    scale = 1.0 + abs(float(np.min(res.margins)))
    assert f_ours <= f_ref + 1e-13 * scale
    # F is known to a few ulps of its terms' size only: that rounding enters the gap too
    rounding = 8.0 * np.finfo(float).eps * (abs(f_ref) + 1.0)
    bound = np.sqrt(2.0 * (max(f_ref - f_ours, 0.0) + rounding) / EPS)
    dist = float(np.linalg.norm(res.u - ref.u))
    assert dist <= bound
    assert abs(float(np.min(res.margins)) - float(np.min(ref.margins))) <= (
        float(np.linalg.norm(a, axis=1).max()) * bound + 1e-12 * scale)
    return dist


def _spy_clarabel_fallbacks(monkeypatch):
    """Count clarabel's max-worst-margin solves."""
    calls = []
    inner = socp.ConePrograms.solve

    def spy(self, kind, *args, **kw):
        if kind.startswith("fallback"):
            calls.append(kind)
        return inner(self, kind, *args, **kw)

    monkeypatch.setattr(socp.ConePrograms, "solve", spy)
    return calls


def _infeasible_instance(rng, m, K, case):
    low, high = -rng.uniform(0.5, 2.0, m), rng.uniform(0.5, 2.0, m)
    a = rng.normal(size=(K, m))
    if case == "duplicates" and K > 1:
        a[K // 2 :] = a[: K - K // 2]  # every row twice (or more)
    elif case == "rank3":  # all rows in a 3-dimensional subspace (one sphere's rows)
        a = rng.normal(size=(K, 3)) @ rng.normal(size=(3, m))
    u_star = rng.uniform(low, high)
    a0 = -(a @ u_star) + rng.uniform(0.0, 1.0, K)
    # a contradicting half-space: a_j u >= -a0_j + 1 beyond the others (infeasible with row 0)
    a = np.vstack([a, -a[0]])
    a0 = np.append(a0, -a0[0] - rng.uniform(0.1, 2.0))
    if case == "duplicates":
        a, a0 = np.vstack([a, a[-1]]), np.append(a0, a0[-1])
    u_nom = rng.uniform(3 * low, 3 * high) if case == "far" else rng.uniform(low, high)
    return low, high, u_nom, a0, a


@pytest.mark.parametrize("case", ["generic", "duplicates", "rank3", "far"])
@pytest.mark.parametrize("seed", range(10))
def test_fallback_equals_clarabel_on_random_infeasible_programs(seed, case, monkeypatch):
    rng = np.random.default_rng(4000 + seed)
    certified = 0
    for K in (1, 2, 5, 20, 60, 100):
        m = int(rng.integers(2, 8))
        low, high, u_nom, a0, a = _infeasible_instance(rng, m, K, case)
        calls = _spy_clarabel_fallbacks(monkeypatch)
        res = SOCPFilter(low, high).solve(u_nom, a0, a)
        assert not res.feasible and res.status.startswith("fallback:")
        assert np.all(res.u >= low) and np.all(res.u <= high)
        certified += not calls
        monkeypatch.undo()
        _check_against_clarabel(res, u_nom, a0, a, low, high)
    assert certified >= 4  # most are the fast path's (the rest clarabel's, also checked)


@pytest.mark.parametrize("K", [21, 100])
def test_fallback_on_the_sphere_arm_equals_clarabel_and_is_certified(K, monkeypatch):
    """The benchmark's sphere-arm states whose QP is infeasible: every one certified (no
    clarabel solve), equal to clarabel's answer within its accuracy."""
    _, _, inst = make_instances(K, 300, learned=False, seed=3)
    low, high = -np.ones(M), np.ones(M)
    f = SOCPFilter(low, high)
    calls = _spy_clarabel_fallbacks(monkeypatch)
    dists, n, ours = [], 0, 0
    for u_nom, a0, a, _ in inst:
        before = len(calls)
        res = f.solve(u_nom, a0, a)
        ours += len(calls) - before
        if res.feasible:
            continue
        n += 1
        assert res.status == "fallback:infeasible"
        dists.append(_check_against_clarabel(res, u_nom, a0, a, low, high))
    assert n >= 5 and ours == 0
    assert np.median(dists) <= 1e-6


def _certified_answer(seed):
    rng = np.random.default_rng(5000 + seed)
    _, _, inst = make_instances(100, 60, learned=False, seed=seed)
    low, high = -np.ones(M), np.ones(M)
    f = SOCPFilter(low, high)
    for u_nom, a0, a, _ in inst:
        if f.solve(u_nom, a0, a).status != "fallback:infeasible":
            continue
        norms = np.linalg.norm(a, axis=1)
        tol = fastpath.FEAS_TOL * fastpath.constraint_scales(a0, a, None, f.bound_norm, norms)
        c_uc = a @ np.clip(u_nom, low, high) + a0
        ldp = fastpath.MaxMarginLDP(u_nom, a0, a, low, high, EPS, norms)
        rows, lower, upper = ldp.active_set(np.arange(a0.size), float(c_uc.min()))
        u, t, mu = fastpath.polish_max_margin(u_nom, a0, a, low, high, EPS, rows, lower,
                                              upper)
        u = np.clip(u, low, high)
        args = (u_nom, a @ u + a0, tol, rows, mu, a[rows], low, high, EPS)
        assert fastpath.certify_max_margin(u, *args)
        return rng, u, t, mu, rows, u_nom, a0, a, tol, low, high
    raise AssertionError("no infeasible state")


@pytest.mark.parametrize("seed", range(4))
def test_certificate_rejects_perturbed_answers(seed):
    rng, u, t, mu, rows, u_nom, a0, a, tol, low, high = _certified_answer(seed)
    assert abs(t - float(np.min(a @ u + a0))) <= 1e-12 * (1.0 + abs(t))

    def ok(v, mu_v):
        return fastpath.certify_max_margin(v, u_nom, a @ v + a0, tol, rows, mu_v, a[rows],
                                           low, high, EPS)

    for size in (1e-6, 1e-8):
        d = rng.normal(size=u.size)
        v = np.clip(u + size * d / np.linalg.norm(d), low, high)
        if np.any(v != u):
            assert not ok(v, mu)
    assert not ok(u, 1.01 * mu)  # multipliers summing to 1.01
    if mu.size > 1:  # the same sum, shifted between two rows: stationarity fails
        shifted = mu.copy()
        shifted[0] += 1e-3
        shifted[1] -= 1e-3
        assert not ok(u, shifted)
    if mu.size > 1:
        neg = mu.copy()
        neg[1] += neg[0] + 1e-9
        neg[0] = -1e-9
        assert not ok(u, neg)


def test_uncertified_answers_go_to_clarabel(monkeypatch):
    """With the certificate refusing everything (or the fast path failing) every infeasible
    state gets clarabel's answer, the same as with the fast path off, and the same status."""
    _, _, inst = make_instances(100, 200, learned=False, seed=4)
    low, high = -np.ones(M), np.ones(M)
    ref = SOCPFilter(low, high, fast_path=False)
    for patch in ("refuse", "raise"):
        if patch == "refuse":
            monkeypatch.setattr(fastpath, "certify_max_margin", lambda *a, **k: False)
        else:
            def boom(*a, **k):
                raise np.linalg.LinAlgError("test")

            monkeypatch.setattr(fastpath, "polish_max_margin", boom)
        calls = _spy_clarabel_fallbacks(monkeypatch)
        f, n = SOCPFilter(low, high), 0
        for u_nom, a0, a, _ in inst:
            res = f.solve(u_nom, a0, a)
            if res.feasible:
                continue
            n += 1
            r = ref.solve(u_nom, a0, a)
            assert res.status == "fallback:infeasible" and not r.feasible
            np.testing.assert_allclose(res.u, r.u, rtol=0, atol=1e-8)
        assert n >= 5 and len(calls) == 2 * n  # ours and the reference's
        monkeypatch.undo()


def test_fallback_without_farkas_rows_and_invalid_input():
    """The fast fallback on all half-spaces (no Farkas working set: a clarabel failure, or
    invalid input with the invalid constraints made vacuous) keeps the statuses."""
    _, _, inst = make_instances(100, 100, learned=False, seed=5)
    low, high = -np.ones(M), np.ones(M)
    f = SOCPFilter(low, high)
    for u_nom, a0, a, _ in inst:
        if f.solve(u_nom, a0, a).feasible:
            continue
        uc = np.clip(u_nom, low, high)
        u_all = f._fast_max_margin(u_nom, uc, a0, a)
        assert u_all is not None
        res = f.solve(u_nom, a0, a)
        np.testing.assert_allclose(u_all, res.u, rtol=0, atol=1e-9)
        bad = a0.copy()
        bad[-1] = np.nan
        inv = f.solve(u_nom, bad, a)
        assert inv.status == "invalid_input" and not inv.feasible
        assert np.isnan(inv.margins[-1]) and np.all(np.isfinite(inv.u))
        ref = SOCPFilter(low, high, fast_path=False, tol=1e-11).solve(u_nom, bad, a)
        assert _objective(inv.u, u_nom, a0[:-1], a[:-1]) <= (
            _objective(ref.u, u_nom, a0[:-1], a[:-1]) + 1e-12)
        break
    else:
        raise AssertionError("no infeasible state")
