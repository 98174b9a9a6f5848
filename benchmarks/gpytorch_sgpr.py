"""Cross-check of the sparse GP numerics against GPyTorch's SGPR (not part of the test suite:
GPyTorch is not a dependency). Run in an environment with torch and gpytorch, from the
repository root::

    PYTHONPATH=. python benchmarks/gpytorch_sgpr.py

It builds the ADP kernel (paper eq. 19) as a GPyTorch kernel on inputs ``[xi, u]``, puts it in an
``InducingPointKernel`` with the same inducing set, and compares, in float64:

1. GPyTorch's SGPR training objective (``ExactMarginalLogLikelihood`` times N, plus the
   ``InducingPointKernelAddedLossTerm``) with ``bound.weighted_bound`` (unit weights), and its
   autograd gradient with ``weighted_bound_and_grad``;
2. the predictive mean and variance with ``sgpr_diagonal_correction`` off and on against VSGP.

What the comparison shows: docs/learners.md ("Conventions against GPyTorch and GPflow").
"""

from __future__ import annotations

import gpytorch
import numpy as np
import torch

from afvsgp_gym.gp import VSGP, ADPKernel
from afvsgp_gym.gp.bound import weighted_bound_and_grad

torch.set_default_dtype(torch.float64)


class ADP(gpytorch.kernels.Kernel):
    """ADP kernel on x = [xi (b), u (m)]: sum_i ubar_i ubar'_i s_i exp(-|xi - xi'|^2_{l_i} / 2)."""

    def __init__(self, b: int, m: int, theta: np.ndarray):
        super().__init__()
        self.b, self.m = b, m
        c = m + 1
        self.log_ls = torch.nn.Parameter(torch.tensor(theta[:c * b].reshape(c, b)))
        self.log_var = torch.nn.Parameter(torch.tensor(theta[c * b:]))

    def forward(self, x1, x2, diag=False, **params):
        b = self.b
        ub1 = torch.cat([torch.ones_like(x1[..., :1]), x1[..., b:]], -1)
        ub2 = torch.cat([torch.ones_like(x2[..., :1]), x2[..., b:]], -1)
        out = 0.0
        for i in range(self.m + 1):
            a1 = x1[..., :b] / self.log_ls[i].exp()
            a2 = x2[..., :b] / self.log_ls[i].exp()
            if diag:
                k = torch.ones(x1.shape[:-1])
                out = out + ub1[..., i] * ub2[..., i] * self.log_var[i].exp() * k
            else:
                d2 = torch.cdist(a1, a2) ** 2
                k = torch.exp(-0.5 * d2)
                out = out + (ub1[..., i, None] * ub2[..., None, :, i] * self.log_var[i].exp() * k)
        return out


class SGPR(gpytorch.models.ExactGP):
    def __init__(self, x, y, lik, base, z):
        super().__init__(x, y, lik)
        self.mean_module = gpytorch.means.ZeroMean()
        self.covar_module = gpytorch.kernels.InducingPointKernel(base, z, lik)
        self.covar_module.inducing_points.requires_grad_(False)

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x),
                                                         self.covar_module(x))


def reproducer():
    rng = np.random.default_rng(1)
    n = 300
    xi = rng.uniform(-2, 2, (n, 3))
    u = rng.uniform(-1.5, 1.5, (n, 1))
    z = (np.sin(xi[:, 0]) + 0.5 * np.cos(1.5 * xi[:, 1]) + 0.075 * xi[:, 2] ** 2
         + (1 + 0.5 * np.sin(xi[:, 2]) + 0.3 * xi[:, 0]) * u[:, 0]
         + 0.1 * rng.standard_normal(n))
    return xi, u, z


def compare(params: np.ndarray, label: str) -> None:
    xi, u, z = reproducer()
    n = len(z)
    v0 = VSGP(num_inducing=20).fit(xi, u, z, learn_hyperparameters=False)
    xo, uo = v0.inducing_xi_, v0.inducing_u_
    kern = ADPKernel(np.ones((2, 3)), np.ones(2)).with_theta(params[:-1])
    s2 = float(np.exp(params[-1]))
    jitter = 0.0  # GPyTorch factors K_uu as it is (it adds jitter only if Cholesky fails)
    ours, grad = weighted_bound_and_grad(params.copy(), kern.clone(), xi, u, z, np.ones(n), xo,
                                         uo, jitter)
    x = torch.tensor(np.hstack([xi, u]))
    y = torch.tensor(z)
    lik = gpytorch.likelihoods.GaussianLikelihood(
        noise_constraint=gpytorch.constraints.GreaterThan(0.0))
    lik.noise = s2
    base = ADP(3, 1, params[:-1])
    model = SGPR(x, y, lik, base, torch.tensor(np.hstack([xo, uo])))
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(lik, model)
    model.train()
    lik.train()
    with gpytorch.settings.max_cholesky_size(10_000):
        loss = mll(model(x), y) * n
        loss.backward()
    # noise = softplus(raw) (+ the constraint's bound 0): d/dlog s2 = grad_raw s2 / sigmoid(raw)
    sig = torch.sigmoid(lik.raw_noise.detach()).item()
    g_t = np.concatenate([base.log_ls.grad.numpy().ravel(), base.log_var.grad.numpy(),
                          [lik.raw_noise.grad.item() * s2 / sig]])
    print(f"[{label}] bound: ours {ours:.12g}, GPyTorch {loss.item():.12g}, "
          f"difference {ours - loss.item():.3g}")
    print(f"[{label}] gradient, max |ours - GPyTorch autograd| = "
          f"{np.max(np.abs(grad - g_t)):.3g} (max |grad| {np.max(np.abs(grad)):.3g})")
    gp = VSGP(kern, s2, inducing=(xo, uo), jitter=0.0).fit(xi, u, z, False)
    xs = np.random.default_rng(5).uniform(-2, 2, (5, 3))
    us = np.random.default_rng(6).uniform(-1.5, 1.5, (5, 1))
    mean, var = gp.predict(xs, us)
    model.eval()
    lik.eval()
    for corr in (False, True):
        with torch.no_grad(), gpytorch.settings.sgpr_diagonal_correction(corr), \
                gpytorch.settings.fast_pred_var(False), \
                gpytorch.settings.max_cholesky_size(10_000):
            model.train()
            model.eval()  # clears the prediction caches
            out = model(torch.tensor(np.hstack([xs, us])))
            m_t, v_t = out.mean.numpy(), out.variance.numpy()
        resid = gp.kernel_.diag(xs, us) - np.einsum(
            "nj,jk,nk->n", kern(xs, us, xo, uo), np.linalg.inv(kern(xo, uo)), kern(xs, us, xo, uo))
        print(f"[{label}] sgpr_diagonal_correction={corr}: max |mean - VSGP| "
              f"{np.max(np.abs(m_t - mean)):.3g}; max |var - VSGP| {np.max(np.abs(v_t - var)):.3g},"
              f" max |var + (k** - Q**) - VSGP| {np.max(np.abs(v_t + resid - var)):.3g}")


if __name__ == "__main__":
    compare(np.array([0.79, 0.55, 8.71, 3.74, 8.65, 3.86, 0.05, 4.14, -3.6]),
            "ill-conditioned (reproducer point)")
    xi, u, z = reproducer()
    fitted = VSGP(num_inducing=20).fit(xi, u, z)
    compare(np.r_[fitted.kernel_.theta, np.log(fitted.noise_variance_)],
            "VSGP.fit with the default prior")
