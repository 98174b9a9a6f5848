"""BarrierConstraints: mixed relative degrees and the braking class-K function, against
high-precision references, finite differences along simulated motions, and the linear chain."""

import mpmath
import numpy as np
import pytest

from afvsgp_gym.cbf.hocbf import HOCBF, BarrierConstraints, braking_alpha
from afvsgp_gym.types import BarrierSet

mpmath.mp.dps = 50


def _alpha_reference(h, a, A):
    """sqrt(2 A h + c^2) - c with c = A / a, odd in h, in 50-digit arithmetic."""
    h, a, A = mpmath.mpf(h), mpmath.mpf(a), mpmath.mpf(A)
    c = A / a
    value = mpmath.sqrt(2 * A * abs(h) + c * c) - c
    return float(mpmath.sign(h) * value), float(mpmath.diff(
        lambda x: mpmath.sign(x) * (mpmath.sqrt(2 * A * abs(x) + c * c) - c), h))


@pytest.mark.parametrize("A", [1e-3, 5.0, 1e6])
@pytest.mark.parametrize("h", [1e-14, 1e-6, 3e-3, 0.15, 2.0, 50.0, -0.04])
def test_braking_alpha_matches_the_braking_curve_to_rounding(h, A):
    """Where 2 A h << c^2 the curve's naive form cancels (sqrt(c^2 + tiny) - c); the
    rationalised form keeps every digit: a few ulp of the 50-digit value, at every scale."""
    a = 4.0
    alpha, slope = braking_alpha(np.array([h]), a, np.array([A]))
    ref, ref_slope = _alpha_reference(h, a, A)
    np.testing.assert_allclose(alpha[0], ref, rtol=4e-16)
    np.testing.assert_allclose(slope[0], ref_slope, rtol=4e-16)


def test_braking_alpha_is_linear_without_a_deceleration_and_bounded_by_it():
    h = np.linspace(-1.0, 3.0, 101)
    alpha, slope = braking_alpha(h, 4.0, np.full(h.shape, np.inf))
    np.testing.assert_array_equal(alpha, 4.0 * h)
    np.testing.assert_array_equal(slope, 4.0)
    hs = np.geomspace(1e-9, 1e4, 500)
    for A in (0.5, 5.0, 50.0):
        alpha, slope = braking_alpha(hs, 4.0, np.full(hs.shape, A))
        assert np.all(alpha * slope < A)  # psi_1 = 0 asks for less than A
        assert np.all(np.diff(alpha) > 0) and np.all(alpha <= 4.0 * hs)  # class K, below a h
        assert alpha[-1] * slope[-1] > 0.98 * A  # and tends to A far away
        # the braking curve shifted by c = A / a: (alpha + c)^2 = 2 A h + c^2
        c = A / 4.0
        np.testing.assert_allclose((alpha + c) ** 2, 2 * A * hs + c * c, rtol=1e-13)


def _double_integrator_psi(cons, row, h0, hd0, u, dt):
    """h'' = u held over dt from (h0, hd0): psi_1 before and after (exact integration)."""
    h1, hd1 = h0 + hd0 * dt + 0.5 * u * dt * dt, hd0 + u * dt
    psi = [cons.psi1(np.array([[h, hd]]))[0] for h, hd in ((h0, hd0), (h1, hd1))]
    return psi


@pytest.mark.parametrize(("h", "hd"), [(0.4, -1.5), (0.02, -0.1), (1e-4, 0.3), (2.0, -3.0)])
def test_degree_two_constraint_is_psi_1_dot_plus_a2_psi_1(h, hd):
    """c0 + c u = d/dt psi_1 + a_2 psi_1 for h'' = lf + lg u: central differences of psi_1
    along the motion (O(dt^2), dt = 1e-6 s)."""
    A, a2 = 5.0, 3.0
    cons = BarrierConstraints([2], (4.0, a2), [A])
    u, lf = 0.7, -1.2
    terms = BarrierSet(np.array([[h, hd]]), np.array([lf]), np.array([[2.0]]), np.zeros((1, 1)))
    c0, c = cons.constraints(terms)
    dt = 1e-6
    acc = lf + 2.0 * u
    before = _double_integrator_psi(cons, 0, h - hd * dt + 0.5 * acc * dt * dt, hd - acc * dt,
                                    acc, dt)
    after = _double_integrator_psi(cons, 0, h, hd, acc, dt)
    psi_dot = (after[1] - before[0]) / (2 * dt)
    psi = cons.psi1(np.array([[h, hd]]))[0]
    np.testing.assert_allclose(c0[0] + c[0, 0] * u, psi_dot + a2 * psi, rtol=1e-7,
                               atol=1e-7 * (abs(psi_dot) + abs(psi)))


def test_mixed_degrees_and_the_linear_chain():
    """Degree 1: c0 = lf + a_1 h (or its own first gain); degree 2 without a deceleration:
    the linear chain's lf + (a1 + a2) h' + a1 a2 h; degree 3: the chain of HOCBF."""
    d = np.array([[0.3, -0.2, 0.0], [0.5, 0.0, 0.0], [0.5, 0.0, 0.0], [0.1, 0.2, -0.3]])
    terms = BarrierSet(d, np.array([1.0, 2.0, 2.0, -1.0]), np.ones((4, 2)), np.zeros((4, 3)))
    cons = BarrierConstraints([2, 1, 1, 3], (4.0, 2.0, 1.5), [np.inf] * 4,
                              first_gain=[np.nan, np.nan, 25.0, np.nan])
    c0, c = cons.constraints(terms)
    np.testing.assert_allclose(c0[0], 1.0 + 6.0 * -0.2 + 8.0 * 0.3, rtol=1e-15)
    np.testing.assert_allclose(c0[1], 2.0 + 4.0 * 0.5, rtol=1e-15)
    np.testing.assert_allclose(c0[2], 2.0 + 25.0 * 0.5, rtol=1e-15)
    chain = HOCBF(3, (4.0, 2.0, 1.5))
    np.testing.assert_allclose(c0[3], -1.0 + chain.offset(d[3]), rtol=1e-15)
    np.testing.assert_array_equal(c, terms.lg)
    np.testing.assert_allclose(cons.margin_gain, [8.0, 4.0, 25.0, 12.0])
    uniform = BarrierConstraints([2, 2], 4.0, [np.inf, np.inf])
    assert uniform.uniform_linear
    two = BarrierSet(d[:2, :2], np.ones(2), np.ones((2, 2)), np.zeros((2, 3)))
    np.testing.assert_array_equal(uniform.constraints(two)[0], HOCBF(2, 4.0).constraints(two)[0])


def test_active_rows_by_distance_and_by_approach():
    """In when h < D or (degree 2) psi_1 < alpha_1(D): the linear case is min(h, h + h'/a_1)
    < D; a barrier approaching fast enters far out; degree 1 by h alone."""
    D = 0.15
    d = np.array([[0.1, 0.0], [0.5, 0.0], [0.5, -2.0], [0.5, -1.3], [0.1, 0.0], [3.0, 0.0]])
    lin = BarrierConstraints([2] * 4 + [1, 1], 4.0, [np.inf] * 6, [D] * 6)
    # h + h'/4: 0.1, 0.5, 0.0, 0.175 (out), and degree 1: 0.1 (in), 3.0 (out)
    np.testing.assert_array_equal(lin.active_rows(d), [0, 2, 4])
    brake = BarrierConstraints([2] * 4 + [1, 1], 4.0, [5.0] * 4 + [np.inf] * 2, [D] * 6)
    alpha_d = braking_alpha(np.array([D]), 4.0, np.array([5.0]))[0][0]
    alpha_h = braking_alpha(np.array([0.5]), 4.0, np.array([5.0]))[0][0]
    expected = [0] + [k for k in (1, 2, 3) if d[k, 1] + alpha_h < alpha_d] + [4]
    np.testing.assert_array_equal(brake.active_rows(d), expected)
    always = BarrierConstraints([1, 2], 4.0, [np.inf, 5.0], [np.inf, np.inf])
    np.testing.assert_array_equal(always.active_rows(np.array([[9.0, 0.0], [9.0, 1.0]])),
                                  [0, 1])


@pytest.mark.parametrize(
    ("args", "match"),
    [(([2], 4.0, [0.0]), "deceleration"), (([1], 4.0, [5.0]), "relative degree 2"),
     (([2], 4.0, [5.0], [-0.1]), "activation"),
     (([3], (1.0, 1.0, 1.0), [np.inf], np.inf, [2.0]), "first_gain"),
     (([2], 4.0, [np.inf], np.inf, [-1.0]), "first_gain")],
)
def test_bad_settings_are_refused(args, match):
    with pytest.raises(ValueError, match=match):
        BarrierConstraints(*args)
