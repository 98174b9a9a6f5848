"""Exact solutions of the safety filter's common cases, each checked by a KKT certificate.

Every function here solves (part of) the filter program of paper eq. 05,

    minimise 1/2 ||u - u_nom||^2   s.t.   c_i(u) = a0_i + a_i @ u - ||G_i ubar|| >= 0,
                                           low <= u <= high,

and returns ``None`` when it cannot: :class:`afvsgp_gym.cbf.SOCPFilter` then solves the cone
program with clarabel. An answer is used only after :func:`certify` accepted it.

- :func:`project_halfspace_box`: one half-space and the box, exact (piecewise-linear root of
  the multiplier, ``u = clip(u_nom + lam a)``).
- :func:`project_polyhedron_box`: any number of half-spaces and the box (the least-distance
  program as a non-negative least-squares problem, Lawson and Hanson 1974, ch. 23).
- :func:`project_cone_box`: one second-order cone and the box (a scalar root of the cone's
  multiplier on a set of box faces, the faces chosen by a primal-dual active set).
- :class:`MaxMarginLDP`, :func:`polish_max_margin`, :func:`certify_max_margin`: the
  infeasible QP's max-worst-margin program (``min -t + eps/2 ||u - u_nom||^2`` s.t. ``a0 + a u
  >= t`` and the box): its active set from a least-distance NNLS, the exact optimum on it,
  and its certificate.

Small arrays (m ~ 7) make numpy's per-call cost dominate: the code calls LAPACK directly
(``dsyev``), keeps scalars as Python floats, multiplies with ``ndarray.dot`` (about half the
call cost of ``@`` at this size) and clips with :func:`clip` (``np.clip``'s Python wrapper costs
more than the clipping).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dgetrf, dgetrs, dsyev
from scipy.optimize import nnls

#: Margin of a certified point: ``c_i(u) >= -FEAS_TOL * scale_i`` (rounding of ``c_i``).
FEAS_TOL = 1e-12
#: A certified point is within ``DIST_TOL * (1 + max|u|)`` of the optimum (:func:`certify`).
DIST_TOL = 1e-9


def clip(u, low, high) -> np.ndarray:
    """``np.clip(u, low, high)`` (NaN propagates) without its wrapper's per-call cost."""
    return np.minimum(np.maximum(u, low), high)


def constraint_scales(a0, a, G, bound_norm: float, norms=None) -> np.ndarray:
    """Size of the terms of ``c_i(u)`` anywhere in the box (``||u|| <= bound_norm``):
    ``|a0_i| + ||a_i|| bound_norm + ||G_i||_F sqrt(1 + bound_norm^2)``. Margins are compared
    with tolerances relative to it (the rounding error of ``c_i`` is a multiple of it).
    ``norms``: the row norms ``||a_i||``, if the caller has them."""
    if norms is None:
        norms = np.sqrt(np.einsum("ij,ij->i", a, a))
    s = np.abs(a0) + norms * bound_norm
    if G is not None:
        s += np.sqrt(np.einsum("ijk,ijk->i", G, G)) * math.sqrt(1.0 + bound_norm**2)
    return s


def cone_margin_gradient(u, a0: float, a, G):
    """``(c(u), grad c(u))`` of one cone constraint: ``c = a0 + a u - ||v||``,
    ``grad c = a - G[:, 1:]' v / ||v||`` with ``v = G ubar`` (gradient None at the apex)."""
    ubar = np.empty(u.size + 1)
    ubar[0] = 1.0
    ubar[1:] = u
    v = G.dot(ubar)
    nv = math.sqrt(float(v.dot(v)))
    c = a0 + float(a.dot(u)) - nv
    if nv == 0.0:
        return c, None
    return c, a - G[:, 1:].T.dot(v) / nv


class Tolerance:
    """``FEAS_TOL * constraint_scales(a0, a, G, bound_norm)``, computed when first needed
    (:meth:`array`) or only for some constraints (:meth:`at`): most calls need none or one."""

    def __init__(self, a0, a, G, bound_norm: float):
        self._args = (a0, a, G, bound_norm)
        self._tol: np.ndarray | None = None

    def array(self) -> np.ndarray:
        if self._tol is None:
            self._tol = FEAS_TOL * constraint_scales(*self._args)
        return self._tol

    def at(self, idx) -> np.ndarray:
        if self._tol is not None:
            return self._tol[idx]
        return np.array([self.one(i) for i in idx.tolist()])

    def one(self, i: int) -> float:
        """The tolerance of constraint ``i`` alone (plain floats)."""
        if self._tol is not None:
            return float(self._tol[i])
        a0, a, G, bound_norm = self._args
        ai = a[i]
        s = abs(float(a0[i])) + math.sqrt(float(ai.dot(ai))) * bound_norm
        if G is not None:
            s += math.sqrt(float(np.vdot(G[i], G[i]))) * math.sqrt(1.0 + bound_norm**2)
        return FEAS_TOL * s


def certify(u, u_nom, margins, tol: Tolerance, active, lam, grads, low, high) -> bool:
    """KKT certificate of ``u`` (inside the box) for the whole program.

    ``margins`` = ``c_i(u)`` for every constraint and ``tol`` their tolerances, ``active``
    the indices with a multiplier ``lam`` (>= 0) and ``grads`` their gradients at ``u``
    (rows). Accepted when every margin is ``>= -tol`` and the distance to the optimum ``u*``
    is provably below ``DIST_TOL (1 + max|u|)``: with the box multipliers taken from
    ``w = u - u_nom - grads' lam`` (positive part at a lower face, negative part at an upper
    face) the Lagrangian is 1-strongly convex, its gradient at ``u`` is the residual ``rho``
    and, for feasible ``u``,

        1/2 ||u* - u||^2 <= lam @ c_active + ||rho|| ||u* - u||
        =>  ||u* - u|| <= ||rho|| + sqrt(||rho||^2 + 2 lam @ c_active).

    Margins within ``tol`` of zero count as zero there: the bound is then the one of the
    program whose ``a0`` differ from the given ones by at most that much (a backward error
    at the rounding level of ``c``).
    """
    lowest = float(margins.min())
    if not lowest >= 0.0:  # only the negative margins need their tolerance
        if lowest != lowest:  # NaN
            return False
        neg = np.flatnonzero(margins < 0.0)
        if not float((margins[neg] + tol.at(neg)).min()) >= 0.0:
            return False
    return _multipliers_ok(u, u_nom, lam, margins[active], tol.at(active), grads, low, high)


def certify_halfspaces(u, u_nom, c, tol, active, lam, a_active, low, high) -> bool:
    """:func:`certify` for half-spaces only (the QP, paper eq. 04): ``c = a0 + a u`` and
    ``tol`` the tolerances of every constraint (arrays), ``active`` the indices with a
    multiplier ``lam`` and ``a_active`` their rows (the same test)."""
    if not float((c + tol).min()) >= 0.0:  # also False for NaN
        return False
    return _multipliers_ok(u, u_nom, lam, c[active], tol[active], a_active, low, high)


def _multipliers_ok(u, u_nom, lam, c_active, tol_active, grads, low, high) -> bool:
    """The multiplier part of :func:`certify`: ``lam >= 0`` and the distance bound, with the
    active margins within their tolerance of zero counted as zero."""
    lam_l = lam.tolist()
    if not min(lam_l, default=0.0) >= 0.0:
        return False
    comp = 0.0
    for li, ci, ti in zip(lam_l, c_active.tolist(), tol_active.tolist(), strict=True):
        if ci > ti:
            comp += li * ci
    return _distance_bound_ok(u, u - u_nom - lam @ grads, comp, low, high)


def certify_one(u, u_nom, c: float, tol: float, lam: float, grad, low, high) -> bool:
    """:func:`certify` for a program with one constraint: its margin ``c``, tolerance ``tol``,
    multiplier ``lam`` and gradient ``grad`` at ``u`` (plain floats; the same test)."""
    if not (c >= -tol and lam >= 0.0):  # also False for NaN
        return False
    return _distance_bound_ok(u, u - u_nom - lam * grad, lam * c if c > tol else 0.0, low,
                              high)


def _distance_bound_ok(u, w, comp: float, low, high) -> bool:
    """The distance bound of :func:`certify`: ``w = u - u_nom - grads' lam`` less the box
    multipliers it implies (its part pushing inwards at a face) is the Lagrangian's gradient
    ``rho``; ``||rho|| + sqrt(||rho||^2 + 2 comp) <= DIST_TOL (1 + max|u|)``."""
    r2, umax = _box_residual(w, u, low, high)
    r = math.sqrt(r2)
    return r + math.sqrt(r2 + 2.0 * comp) <= DIST_TOL * (1.0 + umax)


def _box_residual(w, u, low, high) -> tuple[float, float]:
    """``(||rho||^2, max|u|)``, ``rho`` = ``w`` less its part pushing inwards at a face of
    the box that ``u`` lies on (what the face's multiplier absorbs); NaN if ``u`` is NaN."""
    r2, umax = 0.0, 0.0
    for wj, uj, lj, hj in zip(w.tolist(), u.tolist(), low.tolist(), high.tolist(),
                              strict=True):
        if uj <= lj:
            wj = min(wj, 0.0)
        elif uj >= hj:
            wj = max(wj, 0.0)
        elif not lj < uj < hj:  # NaN
            return math.nan, math.nan
        r2 += wj * wj
        umax = max(umax, abs(uj))
    return r2, umax


def snap_to_box(u, low, high) -> np.ndarray:
    """``u`` clipped to the box, with coordinates within ``1e-13 (high - low)`` of a face
    put on it (so that the face's multiplier is recognised by :func:`certify`)."""
    out = []
    for x, lj, hj in zip(u.tolist(), low.tolist(), high.tolist(), strict=True):
        tol = 1e-13 * (hj - lj)
        out.append(lj if x - lj <= tol else hj if hj - x <= tol else x)
    return np.array(out)


def project_halfspace_box(u_nom, a0: float, a, low, high):
    """``(u, lam)``: projection of ``u_nom`` onto ``{a0 + a @ u >= 0} ∩ [low, high]``.

    ``u(lam) = clip(u_nom + lam a)`` and ``phi(lam) = a0 + a @ u(lam)`` is piecewise linear
    and non-decreasing: coordinate j moves with slope ``a_j^2`` between the values of
    ``lam`` where it enters and leaves the box. The segments are swept in order of ``lam``
    up to the one where ``phi`` reaches 0 (exact root). ``lam = 0`` if the clipped ``u_nom``
    satisfies the half-space; None if no point of the box does.
    """
    un, av, lo, hi = u_nom.tolist(), a.tolist(), low.tolist(), high.tolist()
    phi, slope, events = a0, 0.0, []
    for x, aj, lj, hj in zip(un, av, lo, hi, strict=True):
        phi += aj * min(max(x, lj), hj)
        if aj == 0.0:
            continue
        enter, leave = ((lj - x) / aj, (hj - x) / aj) if aj > 0.0 else ((hj - x) / aj,
                                                                          (lj - x) / aj)
        if leave <= 0.0:
            continue  # at (or past) the face it moves towards
        a2 = aj * aj
        if enter <= 0.0:
            slope += a2
        else:
            events.append((enter, a2))
        events.append((leave, -a2))
    if phi >= 0.0:
        return u_nom.clip(low, high), 0.0
    events.sort()
    lam = 0.0
    for at, change in events:
        if slope > 0.0 and phi + slope * (at - lam) >= 0.0:
            break  # the root is on this segment
        phi += slope * (at - lam)
        lam = at
        slope += change
    else:
        return None  # even the best point of the box violates the half-space
    lam -= phi / slope
    return (u_nom + lam * a).clip(low, high), lam


_M_TEMPLATES: dict[tuple[int, int], np.ndarray] = {}
_E_LAST: dict[int, np.ndarray] = {}  # e_{m+1} (read only)


def _public_nnls(A, b, maxiter):
    return nnls(A, b, maxiter=maxiter)[0]


def _pick_nnls():
    """scipy's compiled Lawson-Hanson routine without the public wrapper's input checks
    (our data are finite float64 C arrays; the wrapper costs about as much as the solve for
    8 x 30 problems) when this scipy has it and it agrees with ``scipy.optimize.nnls`` on a
    test problem; else the public function."""
    try:
        from scipy.optimize._slsqplib import nnls as raw

        A = np.array([[1.0, 0.0, 2.0], [1.0, 1.0, -1.0], [0.0, 1.0, 1.0]])
        b = np.array([2.0, -1.0, 1.0])
        x, _, info = raw(A, b, 30)
        if info == 1 and np.allclose(x, nnls(A, b)[0], rtol=0.0, atol=1e-14):

            def fast(A, b, maxiter):
                x, _, info = raw(A, b, maxiter)
                if info != 1:
                    raise RuntimeError(f"nnls returned info {info}")
                return x

            return fast
    except Exception:  # another scipy: the public function
        pass
    return _public_nnls


_nnls = _pick_nnls()


def project_polyhedron_box(u_nom, a0, a, low, high, norms=None):
    """``(u, lam)``: projection of ``u_nom`` onto ``{a0 + a u >= 0} ∩ [low, high]``, any k.

    With ``x = u - u_nom`` this is the least-distance program ``min ||x|| s.t. E x >= f``
    (rows of ``a`` normalised, the box as ``x >= low - u_nom``, ``-x >= u_nom - high``),
    solved through the non-negative least squares ``min ||[E'; f'] y - e_{m+1}||, y >= 0``:
    ``r = [E'; f'] y - e``, ``x = -r[:m] / r[m]`` and the multipliers are ``y / -r[m]``
    (Lawson and Hanson, ch. 23). ``"infeasible"`` when ``r[m] = 0`` and ``y`` is a Farkas
    certificate: ``y >= 0``, ``f'y = 1 - r[m] > 0`` and ``|E'y| R < f'y`` for the largest
    ``|x| = R`` in the box, so ``y'(Ex - f) < 0`` for every ``x`` there (no point satisfies
    ``Ex >= f``). None if the solver fails or neither holds. ``norms``: the row norms of
    ``a`` with zeros replaced by 1, if the caller has them.
    """
    k, m = a.shape
    tpl = _M_TEMPLATES.get((k, m))
    if tpl is None:
        tpl = np.zeros((m + 1, k + 2 * m))
        tpl[:m, k : k + m] = np.eye(m)
        tpl[:m, k + m :] = -np.eye(m)
        tpl = _M_TEMPLATES[(k, m)] = tpl
    M = tpl.copy()
    if norms is None:
        norms = np.sqrt(np.einsum("ij,ij->i", a, a))
        norms[norms == 0.0] = 1.0
    an = a / norms[:, None]
    M[:m, :k] = an.T
    f = an @ u_nom
    f += a0 / norms
    M[m, :k] = -f
    M[m, k : k + m] = low - u_nom
    M[m, k + m :] = u_nom - high
    e = _E_LAST.get(m)
    if e is None:
        e = _E_LAST[m] = np.zeros(m + 1)
        e[m] = 1.0
    try:
        y = _nnls(M, e, 10 * (k + 2 * m))
    except (RuntimeError, ValueError):
        return None
    r = M @ y
    den = 1.0 - float(r[m])
    if not den > 1e-12:
        reach = math.sqrt(float(np.maximum((high - u_nom) ** 2, (low - u_nom) ** 2).sum()))
        if math.sqrt(float(r[:m] @ r[:m])) * reach < float(r[m]):
            return "infeasible"
        return None
    return snap_to_box(u_nom + r[:m] / den, low, high), y[:k] / (den * norms)


class _Secular:
    """The quadric ``phi(eta) = ubar' W ubar`` along the stationarity path of
    :func:`project_cone_box` (paper eq. 05's cone on its boundary), in the eigenbasis of
    ``W_FF = V diag(d) V'``: ``y = (p + eta s) / (1 - eta d)``, ``phi = W00 + sum (2 s + d y)
    y``, ``t(eta) = t0 + alpha . y``. ``phi`` has a double pole at ``1 / max(d)`` (W has one
    positive eigenvalue); the root search uses ``h = (1 - eta max(d))^2 phi``, which is
    smooth there and has the same roots. Plain floats (lists ``s, d, p, alpha``): m is
    small."""

    def __init__(self, W00: float, s, d, p, t0: float, alpha):
        self.W00, self.t0 = W00, t0
        self.terms = list(zip(s, d, p, alpha, strict=True))
        self.dmax = max(max(d, default=0.0), 0.0)
        self._fractions: tuple | None = None

    def fractions(self):
        """``(phi(inf), [(d_i, d_i r_i^2)])``: the partial fractions ``phi(eta) = phi(inf) +
        sum d_i r_i^2 / (1 - eta d_i)^2``, ``r_i = p_i + s_i / d_i``, ``phi(inf) = W00 - sum
        s_i^2 / d_i`` (terms with ``d_i = s_i = 0`` vanish); None if some ``d_i = 0`` has
        ``s_i != 0`` (then ``phi`` grows linearly in ``eta``). Rounding errors of order
        ``eps s_i^2 / |d_i|``: a start for :meth:`root`, not its answer."""
        if self._fractions is None:
            c, terms = self.W00, []
            for s, d, p, _ in self.terms:
                if d == 0.0:
                    if s != 0.0:
                        self._fractions = (None,)
                        return None
                    continue
                r = p + s / d
                c -= s * s / d
                terms.append((d, d * r * r))
            self._fractions = (c, terms)
        return None if self._fractions[0] is None else self._fractions

    def __call__(self, eta: float) -> tuple[float, float, float, float]:
        """``(h, h', size, t)`` at ``eta``: ``size`` the sum of the absolute terms of ``h``
        (its rounding scale); one pass over the terms."""
        q = 1.0 - eta * self.dmax
        phi, dphi, size, t = self.W00, 0.0, abs(self.W00), self.t0
        for s, d, p, al in self.terms:
            den = 1.0 - eta * d
            y = (p + eta * s) / den
            g = s + d * y
            f = (s + g) * y
            phi += f
            size += abs(f)
            dphi += g * g / den
            t += al * y
        qq = q * q
        return qq * phi, q * (2.0 * q * dphi - 2.0 * self.dmax * phi), qq * size, t

    def root(self, neg: float, pos: float, start: float, max_iter: int = 60):
        """``(eta, t)`` with ``h(eta) = 0`` between ``neg`` (h < 0; ``inf`` if not known yet)
        and ``pos`` (h > 0), both on one side of the pole, from ``start``: each step goes to
        the root of the model fitted at the iterate (:meth:`model_root`), else a Newton step
        on ``h``, else bisection (doubling towards an unknown ``neg``), after a start from
        :meth:`estimate` (then usually one evaluation of ``h`` suffices). A step below
        ``1e-9 |eta|`` ends it (the convergence is quadratic: that step is exact to rounding;
        ``t`` is then the iterate's: only its sign is used)."""
        eta = start if min(neg, pos) <= start < max(neg, pos) else 0.5 * (neg + pos)
        eta = self.estimate(min(neg, pos), max(neg, pos), eta)
        for _ in range(max_iter):
            h, dh, size, t = self(eta)
            if abs(h) <= 1e-14 * size:
                return eta, t
            if h < 0.0:
                neg = eta
            else:
                pos = eta
            lo, hi = min(neg, pos), max(neg, pos)
            nxt = self.model_root(eta, h, dh)
            if not lo <= nxt <= hi:  # eta itself is an end now: a zero step is in
                nxt = eta - h / dh if dh != 0.0 else math.nan
            if lo <= nxt <= hi and abs(nxt - eta) <= 1e-9 * abs(eta):
                return nxt, t
            if hi - lo <= 4e-16 * abs(pos):  # two units in the last place
                return eta, t
            if not lo < nxt < hi:
                if neg == math.inf and eta > 1e6 * pos:
                    return None  # no sign change found this far: give up
                nxt = 0.5 * (neg + pos) if neg < math.inf else 2.0 * max(pos, eta)
            eta = nxt
        return None

    def model_root(self, eta: float, h: float, dh: float) -> float:
        """Root of ``phi ~ A / (1 - eta max(d))^2 + B`` fitted to ``phi`` and ``phi'`` at
        ``eta`` (osculatory rational interpolation: the pole's term plus slowly varying
        ones, the secular-equation device of More and Sorensen 1983 with the constant
        refitted at each step; exact for the pole's term alone), on the iterate's side of
        the pole; NaN if the fit has no root there (or there is no pole)."""
        dmax = self.dmax
        q = 1.0 - eta * dmax
        if not dmax > 0.0 or q == 0.0:
            return math.nan
        qq = q * q
        phi = h / qq
        A = (dh + 2.0 * dmax * q * phi) * q / (2.0 * dmax)  # phi' q^3 / (2 max(d))
        return _pole_model_root(dmax, q, phi, A)

    def estimate(self, lo: float, hi: float, eta: float, max_iter: int = 8) -> float:
        """A start for :meth:`root` in ``(lo, hi)``: the iteration of :meth:`model_root` on the
        partial fractions of ``phi`` (:meth:`fractions`: about half the work per evaluation),
        from ``eta``, until a step below ``1e-12 |eta|``. ``eta`` itself when there are no
        fractions (or no pole) or a step leaves the interval."""
        found = self.fractions()
        dmax = self.dmax
        if found is None or not dmax > 0.0:
            return eta
        c, terms = found
        for _ in range(max_iter):
            phi, half_dphi = c, 0.0
            for d, w in terms:
                den = 1.0 - eta * d
                x = w / (den * den)
                phi += x
                half_dphi += x * d / den
            q = 1.0 - eta * dmax
            nxt = _pole_model_root(dmax, q, phi, half_dphi * q * q * q / dmax)
            if not lo < nxt < hi:
                return eta
            if abs(nxt - eta) <= 1e-12 * abs(eta):
                return nxt
            eta = nxt
        return eta

    def boundary_point(self, start: float):
        """``(eta, t)`` of a root with ``eta >= 0`` and ``t > 0`` (the cone's boundary, not
        the other nappe): ``h`` rises from ``h(0)`` to ``h(1 / max(d)) >= 0``; the root on that
        interval, else one beyond it (beyond it first when ``t(0) < 0``). None if there is
        none."""
        h0, t0 = self.W00, self.t0  # at eta = 0, y = p
        for s, d, p, al in self.terms:
            h0 += (2.0 * s + d * p) * p
            t0 += al * p
        if h0 >= 0.0 and t0 >= 0.0:
            return 0.0, t0
        dmax = self.dmax
        pole = 1.0 / dmax if dmax > 0.0 else math.inf
        if t0 < 0.0 and pole < math.inf:
            # u_nom on the far side (t < 0): the root with t > 0 is usually beyond the pole
            found = self.root_beyond_pole(pole)
            if found is not None and found[1] > 0.0:
                return found
        if h0 < 0.0 and pole < math.inf:  # h(pole) >= 0 (a square times max(d))
            found = self.root(0.0, pole, start)
            if found is not None and found[1] > 0.0:
                return found
        elif h0 < 0.0:
            hi = max(1.0, 2.0 * start)
            for _ in range(60):  # no pole: a point with h > 0
                if self(hi)[0] > 0.0:
                    found = self.root(0.0, hi, start)
                    return found if found is not None and found[1] > 0.0 else None
                hi *= 2.0
        if pole == math.inf:
            return None
        found = self.root_beyond_pole(pole)
        if found is None:  # phi not of that shape: plain Newton on h from the pole
            found = self.root(math.inf, pole, pole * (1.0 + 1e-9))
        return found if found is not None and found[1] > 0.0 else None

    def root_beyond_pole(self, pole: float):
        """``(eta, t)`` of the root right of the pole, where ``phi`` falls from ``+inf`` to
        ``phi_inf = W00 - sum s^2 / d`` (:meth:`root` from ``2 pole``; ~4 evaluations).
        None if ``phi_inf >= 0`` (no root there) or ``phi`` grows linearly in ``eta``."""
        found = self.fractions()
        if found is None or not found[0] < 0.0:  # phi linear in eta, or no root there
            return None
        return self.root(math.inf, pole, 2.0 * pole)


def _pole_model_root(dmax: float, q: float, phi: float, A: float) -> float:
    """Root of ``A / q(eta)^2 + B``, ``q = 1 - eta dmax``, with ``A = phi' q^3 / (2 dmax)``
    and ``B`` fitted to ``phi`` at the point where ``q`` is given (value and slope match
    there), on its side of the pole; NaN if the fit has no root there."""
    B = phi - A / (q * q)
    if not (A > 0.0 and B < 0.0):
        return math.nan
    return (1.0 - math.copysign(math.sqrt(A / -B), q)) / dmax


def project_cone_box(u_nom, a0: float, a, G, low, high, max_rounds: int = 16):
    """``(u, lam)``: projection of ``u_nom`` onto ``{a0 + a u >= ||G ubar||} ∩ [low, high]``.

    On the boundary ``t = a0 + a u = ||v||``, ``v = G ubar``, the cone's multiplier is
    ``lam = eta t`` and stationarity reads ``u - u_nom = eta (W10 + W11 u)`` with
    ``W = abar abar' - G'G``, ``abar = [a0, a]`` (the gradient of ``(t^2 - ||v||^2) / 2``): for a
    fixed ``eta`` a linear system. With some coordinates fixed at box faces, ``W_FF = V
    diag(d) V'`` makes ``ubar' W ubar`` a secular function of ``eta`` whose root
    (:class:`_Secular`) gives ``u``. The faces change one at a time (fix the coordinate
    farthest outside the box, else release the face whose multiplier has the wrong sign),
    starting with none; if that does not settle, once more from the faces (and multiplier)
    of the projection onto the constraint linearised at the clipped ``u_nom``. None when
    neither settles, the root is on the cone's other nappe (``t < 0``) or at its apex
    (``v = 0``: not differentiable; clarabel solves those).
    """
    GtG = G.T.dot(G)
    W11 = a[:, None] * a
    W11 -= GtG[1:, 1:]
    W10 = a0 * a - GtG[1:, 0]
    W00 = a0 * a0 - float(GtG[0, 0])
    m = a.size
    cone = _ConeFaces(u_nom, a0, a, low, high, W00, W10, W11)
    found = cone.settle(np.zeros(m, dtype=bool), None, 0.0, max_rounds)
    if found is not None:
        return found
    uc = clip(u_nom, low, high)
    c_uc, grad = cone_margin_gradient(uc, a0, a, G)
    if grad is None:
        return None
    lin = project_halfspace_box(u_nom, c_uc - float(grad.dot(uc)), grad, low, high)
    if lin is None:
        return None
    u, lam = lin
    t = a0 + float(a.dot(u))
    return cone.settle(u != u_nom + lam * grad, u, lam / t if t > 0.0 else 0.0, max_rounds)


class _ConeFaces:
    """The face iteration of :func:`project_cone_box` (paper eq. 05, one cone and the box)
    for ``W = [[W00, W10'], [W10, W11]]``; the eigensystem with no face fixed is computed
    once per program (both starts of :func:`project_cone_box` use it)."""

    def __init__(self, u_nom, a0: float, a, low, high, W00: float, W10, W11):
        self.u_nom, self.a0, self.a, self.low, self.high = u_nom, a0, a, low, high
        self.W00, self.W10, self.W11 = W00, W10, W11
        self._free: tuple | None = None  # (V, _Secular data) with no face fixed

    def secular(self, fixed, u):
        """``(V, free, u_fixed, (W00', s, d, p, t0', alpha))``: the secular function's data on
        the free coordinates with those in ``fixed`` at their values in ``u``; None if the
        eigensolver fails or no coordinate is free."""
        if not fixed.any():
            if self._free is None:
                d, V, info = dsyev(self.W11)
                if info != 0:
                    return None
                p, s, al = np.array((self.u_nom, self.W10, self.a)).dot(V).tolist()
                self._free = V, (self.W00, s, d.tolist(), p, self.a0, al)
            V, data = self._free
            return V, None, None, data
        F = ~fixed
        if not F.any():
            return None
        uB = np.where(fixed, u, 0.0)
        wb = self.W10 + self.W11.dot(uB)  # linear term on the free coordinates (fixed part)
        d, V, info = dsyev(self.W11[np.ix_(F, F)])
        if info != 0:
            return None
        p, s, al = np.array((self.u_nom, wb, self.a))[:, F].dot(V).tolist()
        c00 = self.W00 + float((self.W10 + wb).dot(uB))
        return V, F, uB, (c00, s, d.tolist(), p, self.a0 + float(self.a.dot(uB)), al)

    def settle(self, fixed, u, eta: float, max_rounds: int):
        """``(u, lam)`` from the faces ``fixed`` (at the values of ``u``) and the multiplier
        estimate ``eta``, or None if the faces do not settle."""
        low, high = self.low, self.high
        lo_l, hi_l = low.tolist(), high.tolist()
        seen = set()
        for _ in range(max_rounds):
            key = fixed.tobytes()
            if key in seen:
                return None
            seen.add(key)
            found = self.secular(fixed, u)
            if found is None:
                return None
            V, F, uB, data = found
            sec = _Secular(*data)
            found = sec.boundary_point(eta)
            if found is None:
                return None
            eta = found[0]
            uF = V.dot([(p + eta * s) / (1.0 - eta * d) for s, d, p, _ in sec.terms])
            if F is None:
                u = uF
            else:
                u = uB
                u[F] = uF
            # primal: fix the coordinate farthest outside the box
            j, worst = -1, 0.0
            for jj, (x, lj, hj) in enumerate(zip(u.tolist(), lo_l, hi_l, strict=True)):
                e = max(lj - x, x - hj)
                if e > worst:
                    j, worst = jj, e
            if j >= 0:
                u = clip(u, low, high)
                fixed[j] = True
                continue
            if F is not None:
                # dual: a face's multiplier w = u - u_nom - eta (W10 + W11 u) must push inwards
                w = u - self.u_nom - eta * (self.W10 + self.W11.dot(u))
                wrong = (np.where(fixed & (u <= low), -w, 0.0)
                         + np.where(fixed & (u >= high), w, 0.0))
                j = int(wrong.argmax())
                if wrong[j] > 0.0:
                    fixed[j] = False
                    continue
            t = self.a0 + float(self.a.dot(u))
            if not t > 0.0:
                return None
            return snap_to_box(u, low, high), eta * t
        return None


_LDP_BOX: dict[int, np.ndarray] = {}  # the box's columns (read only)


class MaxMarginLDP:
    """Active sets of the max-worst-margin program

        minimise  -t + eps/2 ||u - u_nom||^2   s.t.   a0 + a u >= t,   low <= u <= high

    from the least-distance program with ``delta/2 (t - t_ref)^2`` added to the objective
    (then strictly convex in ``(u, t)``): with ``z = (sqrt(eps) (u - u_nom), sqrt(delta) (t -
    T))``, ``T = t_ref + 1/delta``, its objective is ``1/2 ||z||^2`` up to a constant, solved by
    the NNLS of :func:`project_polyhedron_box` (row i: ``(a_i / sqrt(eps)) z_u - z_t /
    sqrt(delta) >= T - a0_i - a_i u_nom``, normalised; the box in ``z_u``). The perturbation
    changes the multipliers' sum from 1 to ``1 - delta (t - t_ref)``: the same active set
    except near degenerate ties; :func:`polish_max_margin` then solves the exact program on
    it. ``delta = eps / max ||a_i||^2`` balances the two parts of each row. The columns of
    every half-space are computed once (:meth:`active_set` takes a working set of them).
    ``norms``: the row norms of ``a`` with zeros replaced by 1."""

    def __init__(self, u_nom, a0, a, low, high, eps: float, norms):
        k, m = a.shape
        big = float(norms.max())
        delta = eps / (big * big)
        inv_n = 1.0 / np.sqrt((norms * norms) * (1.0 / eps) + 1.0 / delta)
        cols = np.empty((k, m + 1))
        np.multiply(a, (inv_n * (1.0 / math.sqrt(eps)))[:, None], out=cols[:, :m])
        cols[:, m] = inv_n * (-1.0 / math.sqrt(delta))
        f = a.dot(u_nom)
        f += a0
        self.cols, self.inv_n = cols, inv_n
        self.g = (1.0 / delta - f) * inv_n  # rhs at t_ref = 0
        box = _LDP_BOX.get(m)
        if box is None:
            box = _LDP_BOX[m] = np.zeros((m + 2, 2 * m))
            box[:m, :m] = np.eye(m)
            box[:m, m:] = -np.eye(m)
        box = box.copy()
        se = math.sqrt(eps)
        box[m + 1, :m] = se * (low - u_nom)
        box[m + 1, m:] = se * (u_nom - high)
        self.box = box
        self.m = m
        e = _E_LAST.get(m + 1)
        if e is None:
            e = _E_LAST[m + 1] = np.zeros(m + 2)
            e[m + 1] = 1.0
        self.e = e

    def active_set(self, work, t_ref: float):
        """``(rows, lower, upper)``: the binding half-spaces among ``work`` (indices) and
        boolean masks of the box faces with a multiplier, for the program with only the
        half-spaces ``work``; None if the NNLS fails."""
        m, k = self.m, work.size
        M = np.empty((m + 2, k + 2 * m))
        M[: m + 1, :k] = self.cols[work].T
        rhs = self.inv_n[work]
        rhs *= t_ref
        rhs += self.g[work]
        M[m + 1, :k] = rhs
        M[:, k:] = self.box
        try:
            y = _nnls(M, self.e, 10 * (k + 2 * m))
        except (RuntimeError, ValueError):
            return None
        return work[y[:k] > 0.0], y[k : k + m] > 0.0, y[k + m :] > 0.0


_BORDERED: dict[int, np.ndarray] = {}


def polish_max_margin(u_nom, a0, a, low, high, eps: float, rows, lower, upper):
    """``(u, t, mu)``: the exact optimum of the max-worst-margin program (see
    :class:`MaxMarginLDP`) with the half-spaces ``rows`` binding (``a0_i + a_i u = t``) and
    the coordinates in the masks ``lower`` / ``upper`` at those faces, the others free (F).

    Stationarity ``eps (u_F - u_nom_F) = a_WF' mu``, ``sum mu = 1``; with ``nu = mu / eps``
    the bordered system ``[[a_WF a_WF', -1], [1', 0]] (nu, t) = (-(a0_W + a_W u_base), 1 /
    eps)``, ``u_base`` = ``u_nom`` with the fixed coordinates on their faces, and ``u_F =
    u_base_F + a_WF' nu``. At an LP vertex ``nu`` is large (~1/eps) and ``a_WF' nu`` a
    difference of large terms (rounding ~1e-11 in ``u``): one step of iterative refinement on
    the binding margins makes them equal to rounding. None if the system is singular
    (linearly dependent binding rows)."""
    free = ~(lower | upper)
    base = np.where(lower, low, np.where(upper, high, u_nom))
    aw = a[rows]
    af = aw[:, free]
    w = rows.size
    S = _BORDERED.get(w)
    if S is None:
        S = np.zeros((w + 1, w + 1))
        S[:w, w] = -1.0
        S[w, :w] = 1.0
        _BORDERED[w] = S
    S = S.copy()
    S[:w, :w] = af.dot(af.T)
    lu, piv, info = dgetrf(S, overwrite_a=1)
    if info != 0:
        return None
    a0w = a0[rows]
    rhs = np.empty(w + 1)
    rhs[:w] = aw.dot(base)
    rhs[:w] += a0w
    rhs[:w] *= -1.0
    rhs[w] = 1.0 / eps
    x, info = dgetrs(lu, piv, rhs)
    if info != 0:
        return None
    nu = x[:w]
    u = base
    u[free] += af.T.dot(nu)
    # refinement: the residual of the binding margins and of the multipliers' sum
    t = float(x[w])
    rhs[:w] = aw.dot(u)
    rhs[:w] += a0w
    rhs[:w] -= t
    rhs[:w] *= -1.0
    rhs[w] = 1.0 / eps - float(nu.sum())
    dx, info = dgetrs(lu, piv, rhs)
    if info != 0:
        return None
    nu += dx[:w]
    u[free] += af.T.dot(dx[:w])
    nu *= eps
    return u, t + float(dx[w]), nu


def certify_max_margin(u, u_nom, c, tol, rows, mu, a_rows, low, high, eps: float) -> bool:
    """KKT certificate of ``u`` (inside the box) for the max-worst-margin program (see
    :class:`MaxMarginLDP`), with ``c = a0 + a u`` for every half-space, ``tol`` their
    tolerances, ``rows`` the binding ones with multipliers ``mu`` and their rows ``a_rows``.

    With ``t = min c`` the pair ``(u, t)`` is feasible. For ``mu >= 0``, ``sum mu = 1``, the
    Lagrangian ``L(u) = eps/2 ||u - u_nom||^2 - mu'(a0 + a u)`` (``t`` drops out) bounds the
    optimum from below over the box, the objective ``F(u) = -min c + eps/2 ||u - u_nom||^2``
    is eps-strongly convex and ``F(u) - L(u) = mu'(c_rows - t)``, so

        eps/2 ||u* - u||^2 <= F(u) - F* <= mu'(c_rows - t) + ||rho||^2 / (2 eps)

    with ``rho`` the Lagrangian's gradient ``eps (u - u_nom) - a_rows' mu`` less its part
    pushing inwards at a box face (as in :func:`certify`). Accepted when ``sum mu`` is 1 to
    rounding and that bound is below ``DIST_TOL (1 + max|u|)``; a binding margin within its
    tolerance of ``t`` counts as equal (the same backward-error convention as :func:`certify`).
    """
    mu_l = mu.tolist()
    if not (min(mu_l, default=-1.0) >= 0.0 and abs(sum(mu_l) - 1.0) <= 1e-12 * len(mu_l)):
        return False
    t = float(c.min())
    if t != t:  # NaN
        return False
    comp = 0.0
    for mi, ci, ti in zip(mu_l, c[rows].tolist(), tol[rows].tolist(), strict=True):
        if ci - t > ti:
            comp += mi * (ci - t)
    r2, umax = _box_residual(eps * (u - u_nom) - mu.dot(a_rows), u, low, high)
    return 2.0 * comp / eps + r2 / (eps * eps) <= (DIST_TOL * (1.0 + umax)) ** 2
