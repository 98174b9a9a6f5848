"""Independent batch formulas for the GP tests (plain numpy loops, no package code)."""

import numpy as np


def rbf_components(ls, var, xi1, xi2):
    """k_i(xi1_n, xi2_j) for every component i: (m+1, N1, N2)."""
    out = np.empty((len(var), len(xi1), len(xi2)))
    for i in range(len(var)):
        d = (xi1[:, None, :] - xi2[None, :, :]) / ls[i]
        out[i] = var[i] * np.exp(-0.5 * np.sum(d * d, axis=2))
    return out


def ubar(u):
    return np.hstack([np.ones((len(u), 1)), u])


def adp_gram(ls, var, xi1, u1, xi2, u2):
    comp = rbf_components(ls, var, xi1, xi2)
    return np.einsum("ni,inj,ji->nj", ubar(u1), comp, ubar(u2))


def weighted_titsias_affine(ls, var, s2, xi, u, z, w, xo, uo, xs, jitter=0.0):
    """DESIGN.md: B = (Koo + s^-2 Kox Lambda Kxo)^-1, r = Kox Lambda z,
    b = s^-2 Kt B r, Sigma = diag(k_i(xs, xs)) - Kt (Koo^-1 - B) Kt'."""
    koo = adp_gram(ls, var, xo, uo, xo, uo) + jitter * np.eye(len(xo))
    kxo = adp_gram(ls, var, xi, u, xo, uo)
    bmat = np.linalg.inv(koo + kxo.T @ (w[:, None] * kxo) / s2)
    r = kxo.T @ (w * z)
    kt = rbf_components(ls, var, xs, xo).transpose(1, 0, 2) * ubar(uo).T[None]  # [N*, m+1, M]
    bvec = kt @ (bmat @ r) / s2
    d = np.linalg.inv(koo) - bmat
    sig = np.diag(var)[None] - kt @ d @ kt.transpose(0, 2, 1)
    return bvec, sig


def exact_affine(ls, var, s2, xi, u, z, xs):
    """Full GP: b = Kt (K + s2 I)^-1 z, Sigma = diag(var) - Kt (K + s2 I)^-1 Kt'."""
    kinv = np.linalg.inv(adp_gram(ls, var, xi, u, xi, u) + s2 * np.eye(len(z)))
    kt = rbf_components(ls, var, xs, xi).transpose(1, 0, 2) * ubar(u).T[None]
    return kt @ (kinv @ z), np.diag(var)[None] - kt @ kinv @ kt.transpose(0, 2, 1)


def synthetic(rng, n, b=3, m=2, noise_std=0.1, gain=1.0):
    """dB(xi, u) = sin(xi_0) + gain u_0 cos(xi_1) + 0.5 u_1 xi_2 (extra dims ignored)."""
    xi = rng.normal(size=(n, b))
    u = rng.uniform(-1.0, 1.0, size=(n, m))
    f = np.sin(xi[:, 0]) + gain * u[:, 0] * np.cos(xi[:, 1 % b])
    if m > 1:
        f = f + 0.5 * u[:, 1] * xi[:, 2 % b]
    return xi, u, f + noise_std * rng.normal(size=n), f
