"""HOCBF chain (paper Definition 3) against an independent symbolic recursion."""

import numpy as np
import pytest

from afvsgp_gym.cbf import HOCBF
from afvsgp_gym.types import BarrierTerms

# h(t) = 2 + sin(t) + 0.5 cos(2t) as coefficients on the basis [1, sin t, cos t, sin 2t, cos 2t]
H0 = np.array([2.0, 1.0, 0.0, 0.0, 0.5])
DERIV = np.array(  # d/dt on that basis
    [
        [0, 0, 0, 0, 0],
        [0, 0, -1, 0, 0],
        [0, 1, 0, 0, 0],
        [0, 0, 0, 0, -2],
        [0, 0, 0, 2, 0],
    ],
    dtype=float,
).T


def _eval(c, t):
    return c @ np.array([1, np.sin(t), np.cos(t), np.sin(2 * t), np.cos(2 * t)])


@pytest.mark.parametrize("r", [1, 2, 3])
def test_psi_chain_and_constraint_match_recursion(r):
    rng = np.random.default_rng(r)
    gains = rng.uniform(0.5, 3.0, size=r)
    cbf = HOCBF(r, gains)
    t = 0.7
    derivs = [H0]
    for _ in range(r):
        derivs.append(DERIV @ derivs[-1])
    psi = [H0]
    for i in range(r):
        psi.append(DERIV @ psi[-1] + gains[i] * psi[-1])
    d = np.array([_eval(c, t) for c in derivs[:r]])
    np.testing.assert_allclose(cbf.psi(d), [_eval(p, t) for p in psi[:r]], rtol=1e-12)
    # S = psi_{r-1}' - h^(r); constraint: h^(r) + S + a_r psi_{r-1} = psi_r
    s_ref = _eval(DERIV @ psi[r - 1], t) - _eval(derivs[r], t)
    np.testing.assert_allclose(cbf.s_term(d), s_ref, rtol=1e-12, atol=1e-12)
    hr = _eval(derivs[r], t)
    terms = BarrierTerms(d, hr - 0.3, np.array([0.3]), np.zeros(1))
    c0, c = cbf.constraint(terms)
    np.testing.assert_allclose(c0 + c @ np.array([1.0]), _eval(psi[r], t), rtol=1e-12)


def test_scalar_gain_broadcasts():
    np.testing.assert_allclose(HOCBF(2, 3.0).gains, [3.0, 3.0])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"relative_degree": 0}, "relative_degree"),
        ({"alpha": [1.0, 2.0, 3.0]}, "alpha"),
        ({"alpha": -1.0}, "positive"),
        ({"alpha": np.nan}, "positive"),
    ],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        HOCBF(**kwargs)


def test_wrong_relative_degree_terms():
    with pytest.raises(ValueError, match="relative degree"):
        HOCBF(2).constraint(BarrierTerms(np.zeros(3), 0.0, np.zeros(1), np.zeros(1)))
