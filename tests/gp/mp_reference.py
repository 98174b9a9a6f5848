"""High-precision references for the sparse GP numerics (mpmath, no package code).

Every quantity is computed from the same float64 inputs (features, actions, targets, weights,
inducing set, log hyperparameters, jitter) in ``DPS``-digit arithmetic with the textbook,
unwhitened formulas and explicit inverses, which are harmless at this precision:

- the weighted Titsias bound through ``Sig = K_oo + S/s2`` (determinant lemma, M x M), and the
  plain N x N formula ``log N(z | 0, Q + s2 Lambda^-1) - ...`` for small N;
- its gradient from the textbook adjoints of the unwhitened form (``dF/dK_oo``, ``dF/dS``,
  ``dF/dr`` with explicit inverses, chained through ``S = K_ox Lambda K_xo``) and, as a check
  of that, by central finite differences with step ``1e-15`` (truncation ~1e-30);
- the affine predictive ``b = Kt Sig^-1 r / s2``, ``Sigma = diag(s) - Kt (K_oo^-1 - Sig^-1) Kt'``.
"""

from __future__ import annotations

import mpmath as mp
import numpy as np

DPS = 40


def _mp_rows(a):
    return [[mp.mpf(float(x)) for x in row] for row in np.atleast_2d(a)]


class MpProblem:
    """A weighted sparse-GP problem held in mpmath; squared coordinate differences are
    precomputed so the bound can be re-evaluated at many hyperparameters."""

    def __init__(self, xi, u, z, weights, xi_o, u_o, dps: int = DPS):
        self.dps = dps
        with mp.workdps(dps):
            self.b = xi.shape[1]
            self.c = u.shape[1] + 1
            self.ub = [[mp.mpf(1)] + r for r in _mp_rows(u)]
            self.ub_o = [[mp.mpf(1)] + r for r in _mp_rows(u_o)]
            self.x = _mp_rows(xi)
            self.xo = _mp_rows(xi_o)
            self.z = [mp.mpf(float(v)) for v in z]
            self.w = [mp.mpf(float(v)) for v in weights]
            self.n, self.m = len(self.x), len(self.xo)
            self.d_xo = self._sqdiff(self.x, self.xo)
            self.d_oo = self._sqdiff(self.xo, self.xo)

    def _sqdiff(self, x1, x2):
        return [[[(a[d] - q[d]) ** 2 for d in range(self.b)] for q in x2] for a in x1]

    def _params(self, theta):
        b, c = self.b, self.c
        th = [mp.mpf(t) for t in theta]
        inv_l2 = [[mp.exp(-2 * th[i * b + d]) for d in range(b)] for i in range(c)]
        var = [mp.exp(th[c * b + i]) for i in range(c)]
        return inv_l2, var

    def _components(self, sq, inv_l2, var):
        """RBF components ``k_i`` (c lists of N1 x N2 nested lists) from squared differences."""
        return [[[var[i] * mp.exp(-mp.fdot(dd, inv_l2[i]) / 2) for dd in row] for row in sq]
                for i in range(self.c)]

    def _gram(self, comp, ub1, ub2):
        """ADP gram (eq. 19) from components."""
        n1, n2 = len(comp[0]), len(comp[0][0])
        out = mp.matrix(n1, n2)
        for n in range(n1):
            for j in range(n2):
                out[n, j] = mp.fsum(ub1[n][i] * ub2[j][i] * comp[i][n][j] for i in range(self.c))
        return out

    def _stats(self, theta, log_s2, jitter, relative):
        inv_l2, var = self._params(theta)
        s2 = mp.exp(mp.mpf(log_s2))
        self._comp_oo = self._components(self.d_oo, inv_l2, var)
        self._comp_xo = self._components(self.d_xo, inv_l2, var)
        koo = self._gram(self._comp_oo, self.ub_o, self.ub_o)
        eps = mp.mpf(float(jitter))
        if relative:
            eps *= mp.fsum(koo[i, i] for i in range(self.m)) / self.m
        for i in range(self.m):
            koo[i, i] += eps
        kxo = self._gram(self._comp_xo, self.ub, self.ub_o)
        cols = [[kxo[n, j] for n in range(self.n)] for j in range(self.m)]
        wcols = [[self.w[n] * col[n] for n in range(self.n)] for col in cols]
        S = mp.matrix(self.m, self.m)
        for i in range(self.m):
            for j in range(i + 1):
                S[i, j] = S[j, i] = mp.fdot(wcols[i], cols[j])
        r = mp.matrix([mp.fdot(wc, self.z) for wc in wcols])
        kdiag = [mp.fsum(self.ub[n][i] ** 2 * var[i] for i in range(self.c))
                 for n in range(self.n)]
        return koo, kxo, S, r, s2, kdiag, var, inv_l2

    def bound(self, theta, log_s2, jitter=0.0, relative=False):
        """Weighted collapsed bound through ``Sig = K_oo + S/s2`` (M x M)."""
        with mp.workdps(self.dps):
            koo, _, S, r, s2, kdiag, _, _ = self._stats(theta, log_s2, jitter, relative)
            sig = koo + S / s2
            kinv = koo ** -1
            wsum = mp.fsum(self.w)
            yy = mp.fdot([w * z for w, z in zip(self.w, self.z, strict=True)], self.z)
            tr_k = mp.fdot(self.w, kdiag)
            tr_q = mp.fsum((kinv * S)[i, i] for i in range(self.m))
            return (-wsum / 2 * mp.log(2 * mp.pi * s2) - mp.log(mp.det(sig)) / 2
                    + mp.log(mp.det(koo)) / 2 - yy / (2 * s2)
                    + (r.T * sig ** -1 * r)[0] / (2 * s2 ** 2) - (tr_k - tr_q) / (2 * s2))

    def bound_dense(self, theta, log_s2, jitter=0.0):
        """The textbook formula with N x N matrices (Titsias 2009, eq. 9, weighted):
        ``log N(z | 0, Q + s2 Lambda^-1) - (sum lambda - N)/2 log(2 pi s2)
        - 1/2 sum log lambda - sum lambda (k_tt - Q_tt) / (2 s2)``."""
        with mp.workdps(self.dps):
            koo, kxo, _, _, s2, kdiag, _, _ = self._stats(theta, log_s2, jitter, False)
            q = kxo * koo ** -1 * kxo.T
            cov = q.copy()
            for t in range(self.n):
                cov[t, t] += s2 / self.w[t]
            zv = mp.matrix(self.z)
            n = self.n
            logpdf = (-n * mp.log(2 * mp.pi) / 2 - mp.log(mp.det(cov)) / 2
                      - (zv.T * cov ** -1 * zv)[0] / 2)
            wsum = mp.fsum(self.w)
            return (logpdf - (wsum - n) / 2 * mp.log(2 * mp.pi * s2)
                    - mp.fsum(mp.log(w) for w in self.w) / 2
                    - mp.fsum(self.w[t] * (kdiag[t] - q[t, t]) for t in range(n)) / (2 * s2))

    def _contract(self, g, comp, sq, ub1, ub2, inv_l2, magnitude=False):
        """``sum_nj g[n, j] dK[n, j] / d(log l, log s)`` for a gram given by ``comp``/``sq``
        (``magnitude``: the same sum of absolute values)."""
        b, c = self.b, self.c
        out = [mp.mpf(0)] * (c * (b + 1))
        for i in range(c):
            for n, row in enumerate(sq):
                for j, dd in enumerate(row):
                    t = g[n, j] * ub1[n][i] * ub2[j][i] * comp[i][n][j]
                    if magnitude:
                        t = abs(t)
                    if not t:
                        continue
                    out[c * b + i] += t
                    for d in range(b):
                        out[i * b + d] += t * dd[d] * inv_l2[i][d]
        return out

    def _adjoints(self, params, jitter, relative):
        """``dF/dK_oo``, ``dF/dK_xo`` (textbook, explicit inverses) and the pieces they need."""
        theta, log_s2 = params[:-1], params[-1]
        koo, kxo, S, r, s2, kdiag, var, inv_l2 = self._stats(theta, log_s2, jitter, relative)
        m, n = self.m, self.n
        kinv = koo ** -1
        sinv = (koo + S / s2) ** -1
        a = sinv * r
        aa = a * a.T
        kis = kinv * S
        g_koo = -sinv / 2 + kinv / 2 - aa / (2 * s2 ** 2) - kis * kinv / (2 * s2)
        g_s = -sinv / (2 * s2) - aa / (2 * s2 ** 3) + kinv / (2 * s2)
        g_r = a / s2 ** 2
        g_kxo = mp.matrix(n, m)
        kg = kxo * g_s
        for t in range(n):
            for j in range(m):
                g_kxo[t, j] = self.w[t] * (2 * kg[t, j] + self.z[t] * g_r[j])
        return dict(koo=koo, kxo=kxo, S=S, r=r, s2=s2, kdiag=kdiag, var=var, inv_l2=inv_l2,
                    kinv=kinv, sinv=sinv, a=a, kis=kis, g_koo=g_koo, g_kxo=g_kxo)

    def bound_sensitivity(self, params, jitter=0.0):
        """First-order change of the bound under relative perturbations of size 1 of every
        kernel entry: ``sum |dF/dK_oo| |K_oo| + sum |dF/dK_xo| |K_xo| + sum lambda k_tt/(2 s2)``
        (times the relative rounding of a float64 kernel entry, the error any float64
        evaluation from float64 kernel values inherits)."""
        with mp.workdps(self.dps):
            d = self._adjoints(params, jitter, False)
            tot = mp.fsum(abs(d["g_koo"][i, j] * d["koo"][i, j])
                          for i in range(self.m) for j in range(self.m))
            tot += mp.fsum(abs(d["g_kxo"][t, j] * d["kxo"][t, j])
                           for t in range(self.n) for j in range(self.m))
            tot += mp.fdot(self.w, d["kdiag"]) / (2 * d["s2"])
            return float(tot)

    def grad_analytic(self, params, jitter=0.0, relative=False, magnitude=False):
        """Gradient w.r.t. ``concat(theta, [log s2])`` from the textbook adjoints (module
        docstring), all inverses explicit. ``magnitude``: instead, per parameter, the sum of
        the absolute values of the terms whose sum the kernel parameters' gradient is (the
        cancellation a float64 evaluation suffers; the last entry is then 0)."""
        with mp.workdps(self.dps):
            d = self._adjoints(params, jitter, relative)
            m, n, b, c = self.m, self.n, self.b, self.c
            S, r, s2, kdiag = d["S"], d["r"], d["s2"], d["kdiag"]
            var, inv_l2, kis, sinv, a = d["var"], d["inv_l2"], d["kis"], d["sinv"], d["a"]
            g_koo, g_kxo = d["g_koo"], d["g_kxo"]
            grad = [x + y for x, y in zip(
                self._contract(g_koo, self._comp_oo, self.d_oo, self.ub_o, self.ub_o, inv_l2,
                               magnitude),
                self._contract(g_kxo, self._comp_xo, self.d_xo, self.ub, self.ub_o, inv_l2,
                               magnitude),
                strict=True)]
            if magnitude:
                return np.array([float(v) for v in grad] + [0.0])
            for i in range(c):  # the diagonal k_tt (variances only)
                grad[c * b + i] -= mp.fsum(self.w[t] * self.ub[t][i] ** 2
                                           for t in range(n)) * var[i] / (2 * s2)
                if relative:  # eps = jitter * mean diag K_oo
                    tr_g = mp.fsum(g_koo[j, j] for j in range(m))
                    grad[c * b + i] += (mp.mpf(float(jitter)) * tr_g / m * var[i]
                                        * mp.fsum(self.ub_o[j][i] ** 2 for j in range(m)))
            yy = mp.fdot([w * z for w, z in zip(self.w, self.z, strict=True)], self.z)
            tr_k = mp.fdot(self.w, kdiag)
            tr_q = mp.fsum(kis[i, i] for i in range(m))
            ra = (r.T * a)[0]
            asa = (a.T * S * a)[0]
            tr_sig_s = mp.fsum((sinv * S)[i, i] for i in range(m))
            d_s2 = (-mp.fsum(self.w) / (2 * s2) + tr_sig_s / (2 * s2 ** 2) + yy / (2 * s2 ** 2)
                    - ra / s2 ** 3 + asa / (2 * s2 ** 4) + (tr_k - tr_q) / (2 * s2 ** 2))
            return np.array([float(v) for v in grad] + [float(d_s2 * s2)])

    def grad(self, params, jitter=0.0, relative=False, h="1e-15"):
        """Central finite differences of :meth:`bound` in ``DPS`` digits w.r.t.
        ``concat(theta, [log s2])`` (all float64 inputs; the step is exact in mpmath)."""
        with mp.workdps(self.dps):
            step = mp.mpf(h)
            out = []
            for j in range(len(params)):
                hi = [mp.mpf(float(v)) for v in params]
                lo = list(hi)
                hi[j] += step
                lo[j] -= step
                out.append((self.bound(hi[:-1], hi[-1], jitter, relative)
                            - self.bound(lo[:-1], lo[-1], jitter, relative)) / (2 * step))
            return np.array([float(v) for v in out])

    def affine(self, theta, log_s2, jitter, xs):
        """Affine predictive (eq. 20) at the rows of ``xs``: ``b`` (N*, m+1), ``Sigma``."""
        with mp.workdps(self.dps):
            koo, _, S, r, s2, _, var, inv_l2 = self._stats(theta, log_s2, jitter, False)
            sig_inv = (koo + S / s2) ** -1
            d_mat = koo ** -1 - sig_inv
            wv = sig_inv * r / s2
            sq = self._sqdiff(_mp_rows(xs), self.xo)
            bs, sigmas = [], []
            for row in sq:
                kt = mp.matrix(self.c, self.m)
                for i in range(self.c):
                    for j in range(self.m):
                        kt[i, j] = (var[i] * mp.exp(-mp.fdot(row[j], inv_l2[i]) / 2)
                                    * self.ub_o[j][i])
                bvec = kt * wv
                sig = -(kt * d_mat * kt.T)
                for i in range(self.c):
                    sig[i, i] += var[i]
                bs.append([float(bvec[i]) for i in range(self.c)])
                sigmas.append([[float(sig[i, j]) for j in range(self.c)] for i in range(self.c)])
            return np.array(bs), np.array(sigmas)

    def condition(self, theta, log_s2, jitter):
        """Condition numbers (2-norm) of ``K_oo`` and ``K_oo + S/s2`` (from mp eigenvalues)."""
        with mp.workdps(self.dps):
            koo, _, S, _, s2, _, _, _ = self._stats(theta, log_s2, jitter, False)
            out = []
            for a in (koo, koo + S / s2):
                ev = mp.eigsy(a, eigvals_only=True)
                ev = [abs(e) for e in ev]
                out.append(float(max(ev) / min(ev)))
            return tuple(out)

    def affine_rounding_bound(self, theta, log_s2, jitter, xs):
        """First-order bound on the error of the affine predictive (eq. 20) caused by a
        relative perturbation ``gamma_{N+M}`` of every sum that forms ``K_oo + S/s2`` and
        ``r`` (what rounding does to a learner that accumulates ``S``, and what a backward
        stable factorisation of ``K_oo + S/s2`` adds), per unit ``gamma``:
        ``|Kt Sig^-1| (|K_ox| |z| + (|K_oo| + |K_ox| |K_xo| / s2) |w| s2) / s2`` for ``b`` and
        ``|Kt Sig^-1| (|K_oo| + |K_ox| |K_xo| / s2) |Sig^-1 Kt'|`` for Sigma. Returns
        ``(tol_b (N*, m+1), tol_sigma (N*, m+1, m+1))`` as float64 (multiply by gamma)."""
        with mp.workdps(self.dps):
            koo, kxo, S, r, s2, _, var, inv_l2 = self._stats(theta, log_s2, jitter, False)
            sig_inv = (koo + S / s2) ** -1
            w = sig_inv * r / s2
            akxo = np.array([[abs(float(kxo[n, j])) for j in range(self.m)]
                             for n in range(self.n)])
            akoo = np.array([[abs(float(koo[i, j])) for j in range(self.m)]
                             for i in range(self.m)])
            az = np.abs(np.array([float(v) for v in self.z]))
            aw = np.abs(np.array([float(v) for v in w]))
            wts = np.array([float(v) for v in self.w])
            s2f = float(s2)
            pert = akoo + akxo.T @ (wts[:, None] * akxo) / s2f  # |delta Sig| per unit gamma
            pert_r = akxo.T @ (wts * az)
            sq = self._sqdiff(_mp_rows(xs), self.xo)
            tb, ts = [], []
            for row in sq:
                kt = mp.matrix(self.c, self.m)
                for i in range(self.c):
                    for j in range(self.m):
                        kt[i, j] = (var[i] * mp.exp(-mp.fdot(row[j], inv_l2[i]) / 2)
                                    * self.ub_o[j][i])
                ks = np.abs(np.array((kt * sig_inv).tolist(), dtype=float))  # |Kt Sig^-1|
                tb.append(ks @ (pert_r / s2f + pert @ aw))
                ts.append(ks @ pert @ ks.T)
            return np.array(tb), np.array(ts)
