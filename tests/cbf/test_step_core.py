"""The controller's compiled per-step arithmetic (afvsgp_gym.cbf._step) against its numpy
versions and independent bounds: the cone matrices' Cholesky factor by its backward error at
cond 1e12, the exploration gate and scale in the cases that decide it, bad input."""

import numpy as np
import pytest

from afvsgp_gym.cbf import exploration
from afvsgp_gym.cbf.controller import cone_matrices
from afvsgp_gym.cbf.exploration import exploration_scale

needs_core = pytest.mark.skipif(exploration._step is None, reason="_step not built")
EPS = np.finfo(np.float64).eps


def _covariances(rng, n, c, cond):
    """``n`` symmetric positive definite (c, c) matrices of condition number ``cond``, made
    slightly unsymmetric (the filter symmetrises them)."""
    out = np.empty((n, c, c))
    for r in range(n):
        q, _ = np.linalg.qr(rng.normal(size=(c, c)))
        s = (q * np.logspace(0, -np.log10(cond), c)) @ q.T
        out[r] = s + 1e-3 * EPS * rng.normal(size=(c, c))
    return out


@needs_core
@pytest.mark.parametrize("cond", [1e2, 1e12])
def test_cone_factors_have_cholesky_backward_error(cond):
    """G = beta U with U'U = (S + S')/2: the Cholesky backward error bound |U'U - A| <=
    gamma_{c+1} |U'| |U| (Higham, Thm 10.3) holds elementwise, conditioning aside; U is upper
    triangular; and it agrees with the numpy (LAPACK) factor to ~cond eps."""
    rng = np.random.default_rng(0)
    n, c, beta = 6, 8, 1.7
    sig = _covariances(rng, n, c, cond)
    got = cone_matrices(sig, beta, backend="compiled")
    ref = cone_matrices(sig, beta, backend="numpy")
    sym = 0.5 * (sig + sig.transpose(0, 2, 1))
    gamma = (c + 1) * EPS / (1 - (c + 1) * EPS)
    for g, a in zip(got, sym, strict=True):
        u = g / beta
        assert np.all(np.tril(u, -1) == 0.0)
        bound = 2 * gamma * np.abs(u.T) @ np.abs(u) + 4 * EPS * np.abs(a)
        assert np.all(np.abs(u.T @ u - a) <= bound)
    assert np.max(np.abs(got - ref)) <= 10 * c * cond * EPS * np.max(np.abs(ref))


@needs_core
def test_cone_factors_not_positive_definite_take_the_numpy_path():
    """A covariance with a negative eigenvalue (or NaN) is factored as the numpy version
    does it (the eigen-factor of its positive part; NaN stays in it, for the cone program to
    flag)."""
    rng = np.random.default_rng(1)
    sig = _covariances(rng, 3, 8, 1e3)
    sig[1] -= 0.01 * np.eye(8)  # eigenvalues down to -0.01
    np.testing.assert_array_equal(cone_matrices(sig, 2.0, backend="compiled"),
                                  cone_matrices(sig, 2.0, backend="numpy"))
    sig[2, 3, 3] = np.nan
    np.testing.assert_array_equal(cone_matrices(sig, 2.0, backend="compiled"),
                                  cone_matrices(sig, 2.0, backend="numpy"))
    assert np.isnan(cone_matrices(sig, 2.0)[2]).any()


@pytest.mark.parametrize("backend", ["compiled", "numpy"])
def test_zero_covariances_get_zero_factors_and_the_rest_stays_batched(backend):
    """A zero covariance (a projected row W_k = 0: the shared learner's error cannot reach
    the barrier) has the zero factor, as the one-by-one eigen-factor gives it; the others are
    factored as they are without it, bit for bit."""
    if backend == "compiled" and exploration._step is None:
        pytest.skip("_step not built")
    from afvsgp_gym.cbf.controller import cone_matrix

    rng = np.random.default_rng(2)
    sig = _covariances(rng, 5, 8, 1e4)
    sig[[1, 3]] = 0.0
    got = cone_matrices(sig, 2.5, backend=backend)
    np.testing.assert_array_equal(got[[1, 3]], 0.0)
    np.testing.assert_array_equal(got[[1, 3]], np.array([cone_matrix(s, 2.5)
                                                         for s in sig[[1, 3]]]) + 0.0)
    np.testing.assert_array_equal(got[[0, 2, 4]],
                                  cone_matrices(sig[[0, 2, 4]], 2.5, backend=backend))
    np.testing.assert_array_equal(cone_matrices(np.zeros((3, 8, 8)), 2.5, backend=backend),
                                  0.0)


def _gate_case(rng, n=6, m=7):
    sig = _covariances(rng, n, m + 1, 1e4) * 0.5
    a0 = rng.normal(size=n)
    a = rng.normal(size=(n, m))
    u_nom = rng.uniform(-2, 2, m)
    low, high = -np.ones(m), np.ones(m)
    noise = 0.1 * rng.uniform(size=n)
    return sig, a0, a, u_nom, low, high, noise, 0.5 * (high - low)


@needs_core
def test_exploration_scale_agrees_with_numpy_and_the_formula():
    """Random cases (gated or not): the compiled scale equals the numpy one to a few eps,
    and, when some barrier is gated, the formula sqrt(sum_i h_i^2 Sigma_uu,ii) / ||h a|| of
    the gated barrier with the largest value, evaluated here by explicit loops."""
    rng = np.random.default_rng(2)
    gated_cases = 0
    for _ in range(200):
        args = _gate_case(rng)
        thr, reach = rng.uniform(0, 6), rng.uniform(0, 4)
        got = exploration_scale(*args, thr, reach, backend="compiled")
        ref = exploration_scale(*args, thr, reach, backend="numpy")
        sig, a0, a, u_nom, low, high, noise, h = args
        u = np.clip(u_nom, low, high)
        ub = np.concatenate([[1.0], u])
        best = -1.0
        for k in range(len(a0)):
            std = np.sqrt(max(sum(ub[i] * sig[k, i, j] * ub[j] for i in range(8)
                                  for j in range(8)), 0.0))
            if std > thr * noise[k] and a0[k] + a[k] @ u < reach * std:
                var = sum(h[i] ** 2 * sig[k, i + 1, i + 1] for i in range(7))
                best = max(best, np.sqrt(var) / np.sqrt(sum((a[k] * h) ** 2)))
        if best < 0:
            assert got == ref == -1.0
        else:
            gated_cases += 1
            assert abs(got - best) <= 50 * EPS * best
            assert abs(ref - best) <= 50 * EPS * best
    assert gated_cases >= 50


@needs_core
@pytest.mark.parametrize("backend", ["compiled", "numpy"])
def test_exploration_scale_zero_gain(backend):
    """A gated barrier with a zero action gain: rho = inf (full noise); with a zero action
    covariance too, 0/0 = NaN, which the noise counts as full as well."""
    rng = np.random.default_rng(3)
    sig, a0, a, u_nom, low, high, noise, h = _gate_case(rng, n=2)
    a0[:] = -10.0  # deciding
    noise[:] = 0.0  # uncertain wherever std > 0
    a[0] = 0.0
    args = (sig, a0, a, u_nom, low, high, noise, h, 1.0, 4.0)
    assert exploration_scale(*args, backend=backend) == np.inf
    sig[0, 1:, :] = sig[0, :, 1:] = 0.0  # only the constant's variance left
    sig[1] = 0.0  # barrier 1 certain: not gated
    assert np.isnan(exploration_scale(*args, backend=backend))


@needs_core
def test_bad_input_to_the_step_core_is_refused():
    from afvsgp_gym.cbf import _step

    n, m = 2, 7
    c = m + 1
    with pytest.raises(ValueError, match="sigma"):
        _step.cone_factors(n, c, np.zeros((n, c, c - 1)), 1.0, np.zeros((n, c, c)))
    with pytest.raises(ValueError, match="out"):
        _step.cone_factors(n, c, np.zeros((n, c, c)), 1.0, np.zeros((n, c, c), np.float32))
    with pytest.raises(ValueError, match="sigma"):
        _step.cone_factors(n, 18, np.zeros((n, 18, 18)), 1.0, np.zeros((n, 18, 18)))
    args = dict(sigma=np.zeros((n, c, c)), a0=np.zeros(n), a=np.zeros((n, m)),
                u_nom=np.zeros(m), low=-np.ones(m), high=np.ones(m), noise_std=np.zeros(n),
                half_range=np.ones(m))
    for name, bad in [("a0", np.zeros(n + 1)), ("noise_std", np.zeros(n, dtype=int)),
                      ("half_range", np.ones(m - 1))]:
        with pytest.raises(ValueError, match=name):
            _step.exploration_scale(n, m, *{**args, name: bad}.values(), 1.0, 2.0)


def test_without_the_core_the_numpy_versions_run(without_extensions):
    """Built without a C compiler (no _step), both functions give the numpy answers."""
    rng = np.random.default_rng(4)
    args = _gate_case(rng)
    sig = args[0]
    want_g = cone_matrices(sig, 1.5, backend="numpy")
    want_s = exploration_scale(*args, 1.0, 4.0, backend="numpy")
    without_extensions("step")
    np.testing.assert_array_equal(cone_matrices(sig, 1.5), want_g)
    assert exploration_scale(*args, 1.0, 4.0) == want_s
