"""ADP compound kernel: brute-force formula, PSD, diag, cross_affine, gradients.
Tolerances: tests/gp/tolerances.py (the relative rounding of a kernel entry, ``kernel_rtol``)."""

import numpy as np
import pytest
from tolerances import assert_within, central_difference, gamma, kernel_rtol

from afvsgp_gym.gp._linalg import ubar
from afvsgp_gym.gp.kernels import ADPKernel


def _kernel(rng, b=4, m=2):
    return ADPKernel(rng.uniform(0.5, 2.0, (m + 1, b)), rng.uniform(0.3, 2.0, m + 1))


def _brute(kern, xi1, u1, xi2, u2):
    ls, var = kern.lengthscales, kern.variances
    out = np.zeros((len(xi1), len(xi2)))
    for n in range(len(xi1)):
        for j in range(len(xi2)):
            ub1 = np.concatenate([[1.0], u1[n]])
            ub2 = np.concatenate([[1.0], u2[j]])
            for i in range(len(var)):
                d = (xi1[n] - xi2[j]) / ls[i]
                out[n, j] += ub1[i] * ub2[i] * var[i] * np.exp(-0.5 * d @ d)
    return out


def test_gram_matches_brute_force():
    rng = np.random.default_rng(0)
    k = _kernel(rng)
    xi1, u1 = rng.normal(size=(5, 4)), rng.normal(size=(5, 2))
    xi2, u2 = rng.normal(size=(3, 4)), rng.normal(size=(3, 2))
    # both evaluations round each entry by at most kernel_rtol (relative to the sum of the
    # absolute values of its m+1 component terms)
    mag = np.abs(_brute(k, xi1, np.abs(u1), xi2, np.abs(u2)))
    tol = 2 * kernel_rtol(k, xi1, xi2) * mag
    assert_within(k(xi1, u1, xi2, u2), _brute(k, xi1, u1, xi2, u2), tol, "cross gram")
    mag = np.abs(_brute(k, xi1, np.abs(u1), xi1, np.abs(u1)))
    assert_within(k(xi1, u1), _brute(k, xi1, u1, xi1, u1), 2 * kernel_rtol(k, xi1) * mag,
                  "gram")


def test_gram_is_psd_and_symmetric():
    rng = np.random.default_rng(1)
    k = _kernel(rng, b=3, m=3)
    xi, u = rng.normal(size=(40, 3)), rng.normal(size=(40, 3))
    gram = k(xi, u)
    np.testing.assert_array_equal(gram, gram.T)
    # PSD up to the entries' rounding (Weyl: |dlambda| <= |dK|_2 <= N max|dK_ij|) and
    # eigvalsh's own error gamma(N) |K|_2
    n = len(gram)
    norm = np.linalg.norm(gram, 2)
    mag = np.max(np.abs(k(xi, np.abs(u))))
    assert np.linalg.eigvalsh(gram).min() >= -(n * kernel_rtol(k, xi) * mag + gamma(n) * norm)


def test_diag_matches_full():
    rng = np.random.default_rng(2)
    k = _kernel(rng)
    xi, u = rng.normal(size=(7, 4)), rng.normal(size=(7, 2))
    mag = k.diag(xi, np.abs(u))  # sum of the component terms' absolute values
    assert_within(k.diag(xi, u), np.diag(k(xi, u)), 2 * kernel_rtol(k, xi) * mag, "diag")


def test_components_and_cross_affine_compose_to_gram():
    rng = np.random.default_rng(3)
    k = _kernel(rng)
    xs, us = rng.normal(size=(6, 4)), rng.normal(size=(6, 2))
    x2, u2 = rng.normal(size=(4, 4)), rng.normal(size=(4, 2))
    comp = k.components(xs, x2)
    assert comp.shape == (3, 6, 4)
    cross = k.cross_affine(xs, x2, u2)
    assert cross.shape == (6, 3, 4)
    via_cross = np.einsum("ni,nij->nj", ubar(us), cross)
    mag = np.abs(k(xs, np.abs(us), x2, np.abs(u2)))
    assert_within(via_cross, k(xs, us, x2, u2), 2 * kernel_rtol(k, xs, x2) * mag, "composed")
    # the same component times the same factor: one rounding of the product
    assert_within(cross[:, 1, :], comp[1] * u2[:, 0][None, :],
                  gamma(1) * np.abs(comp[1] * u2[:, 0][None, :]), "component")


def test_theta_is_log_parametrisation_and_roundtrips():
    rng = np.random.default_rng(4)
    k = _kernel(rng)
    th = k.theta
    assert th.shape == (k.n_params,) == (3 * 5,)
    np.testing.assert_allclose(np.exp(th[:12]).reshape(3, 4), k.lengthscales)
    np.testing.assert_allclose(np.exp(th[12:]), k.variances)
    k2 = k.with_theta(th + 0.1)
    np.testing.assert_allclose(k2.variances, k.variances * np.exp(0.1))
    np.testing.assert_array_equal(k.theta, th)  # original untouched


@pytest.mark.parametrize("same", [True, False])
def test_grad_contract_matches_finite_differences(same):
    rng = np.random.default_rng(5)
    k = _kernel(rng, b=3, m=2)
    xi1, u1 = rng.normal(size=(5, 3)), rng.normal(size=(5, 2))
    xi2, u2 = (None, None) if same else (rng.normal(size=(4, 3)), rng.normal(size=(4, 2)))
    g = rng.normal(size=(5, 5 if same else 4))

    def f(theta):
        gram = k.with_theta(theta)(xi1, u1, xi2, u2)
        return float(np.sum(g * gram)), float(np.sum(np.abs(g * gram)))

    ana = k.grad_contract(g, xi1, ubar(u1), xi2, None if same else ubar(u2))
    fd, err = central_difference(f, k.theta, 1e-4)
    assert_within(ana, fd, err + gamma(g.size) * np.abs(ana), "gradient")


def test_grad_diag_contract_matches_finite_differences():
    rng = np.random.default_rng(6)
    k = _kernel(rng, b=3, m=2)
    xi, u = rng.normal(size=(6, 3)), rng.normal(size=(6, 2))
    g = rng.normal(size=6)
    ana = k.grad_diag_contract(g, ubar(u))

    def f(theta):
        d = k.with_theta(theta).diag(xi, u)
        return float(g @ d), float(np.abs(g) @ d)

    fd, err = central_difference(f, k.theta, 1e-4)
    assert_within(ana, fd, err + gamma(g.size) * np.abs(ana), "gradient")


def test_from_data_gives_prior_variance_near_data_variance():
    rng = np.random.default_rng(7)
    xi, u = rng.normal(size=(200, 5)) * 3.0, rng.normal(size=(200, 2))
    z = 2.0 * rng.normal(size=200)
    k = ADPKernel.from_data(xi, u, z)
    assert k.lengthscales.shape == (3, 5) and k.variances.shape == (3,)
    ratio = np.mean(k.diag(xi, u)) / np.var(z)
    assert 0.7 < ratio < 1.3  # a heuristic: the prior variance matches var(z) within 30 %


@pytest.mark.parametrize("bad", [
    dict(lengthscales=-np.ones((2, 3)), variances=np.ones(2)),
    dict(lengthscales=np.ones((2, 3)), variances=np.ones(3)),
    dict(lengthscales=np.ones((2, 3)), variances=np.array([1.0, np.nan])),
])
def test_constructor_rejects_bad_parameters(bad):
    with pytest.raises(ValueError):
        ADPKernel(**bad)


def test_call_rejects_bad_shapes_naming_argument():
    k = ADPKernel(np.ones((3, 4)), np.ones(3))
    with pytest.raises(ValueError, match="xi"):
        k(np.ones((2, 5)), np.ones((2, 2)))
    with pytest.raises(ValueError, match="u"):
        k(np.ones((2, 4)), np.ones((3, 2)))
