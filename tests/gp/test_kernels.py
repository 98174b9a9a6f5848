"""ADP compound kernel: brute-force formula, PSD, diag, cross_affine, gradients."""

import numpy as np
import pytest

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
    np.testing.assert_allclose(k(xi1, u1, xi2, u2), _brute(k, xi1, u1, xi2, u2), rtol=1e-12)
    np.testing.assert_allclose(k(xi1, u1), _brute(k, xi1, u1, xi1, u1), rtol=1e-12, atol=1e-14)


def test_gram_is_psd_and_symmetric():
    rng = np.random.default_rng(1)
    k = _kernel(rng, b=3, m=3)
    xi, u = rng.normal(size=(40, 3)), rng.normal(size=(40, 3))
    gram = k(xi, u)
    np.testing.assert_array_equal(gram, gram.T)
    assert np.linalg.eigvalsh(gram).min() > -1e-10 * np.abs(gram).max()


def test_diag_matches_full():
    rng = np.random.default_rng(2)
    k = _kernel(rng)
    xi, u = rng.normal(size=(7, 4)), rng.normal(size=(7, 2))
    np.testing.assert_allclose(k.diag(xi, u), np.diag(k(xi, u)), rtol=1e-13)


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
    np.testing.assert_allclose(via_cross, k(xs, us, x2, u2), rtol=1e-12)
    np.testing.assert_allclose(cross[:, 1, :], comp[1] * u2[:, 0][None, :], rtol=1e-13)


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
        return float(np.sum(g * k.with_theta(theta)(xi1, u1, xi2, u2)))

    ana = k.grad_contract(g, xi1, ubar(u1), xi2, None if same else ubar(u2))
    th = k.theta
    eps = 1e-6
    fd = np.array([(f(th + eps * e) - f(th - eps * e)) / (2 * eps) for e in np.eye(len(th))])
    np.testing.assert_allclose(ana, fd, rtol=1e-6, atol=1e-8)


def test_grad_diag_contract_matches_finite_differences():
    rng = np.random.default_rng(6)
    k = _kernel(rng, b=3, m=2)
    xi, u = rng.normal(size=(6, 3)), rng.normal(size=(6, 2))
    g = rng.normal(size=6)
    ana = k.grad_diag_contract(g, ubar(u))
    th = k.theta
    eps = 1e-6
    fd = np.array([(g @ k.with_theta(th + eps * e).diag(xi, u)
                    - g @ k.with_theta(th - eps * e).diag(xi, u)) / (2 * eps)
                   for e in np.eye(len(th))])
    np.testing.assert_allclose(ana, fd, rtol=1e-6, atol=1e-8)


def test_from_data_gives_prior_variance_near_data_variance():
    rng = np.random.default_rng(7)
    xi, u = rng.normal(size=(200, 5)) * 3.0, rng.normal(size=(200, 2))
    z = 2.0 * rng.normal(size=200)
    k = ADPKernel.from_data(xi, u, z)
    assert k.lengthscales.shape == (3, 5) and k.variances.shape == (3,)
    ratio = np.mean(k.diag(xi, u)) / np.var(z)
    assert 0.7 < ratio < 1.3


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
