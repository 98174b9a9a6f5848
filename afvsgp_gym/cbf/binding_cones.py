"""Projection onto a few second-order cones that all bind, and the box (paper eq. 05).

With every cone ``c_i(u) = a0_i + a_i u - ||v_i||`` (``v_i = G_i ubar``) on its boundary and the
coordinates ``B`` on box faces, the KKT conditions of ``min 1/2 ||u - u_nom||^2`` on the free
coordinates ``F`` are the square system

    u_F - u_nom_F - sum_i lam_i grad_F c_i(u) = 0,    c_i(u) = 0   (i = 1..k),

solved by Newton's method in ``(u_F, lam)`` (sequential quadratic programming with the exact
Hessian): ``grad c_i = a_i - w_i``, ``hess c_i = -(B_i' B_i - w_i w_i') / ||v_i||`` with
``B_i = G_i[:, 1:]`` and ``w_i = B_i' v_i / ||v_i||``, so the Lagrangian's Hessian ``H = I -
sum_i lam_i hess c_i`` is positive definite for ``lam >= 0`` (the constraints are concave;
an iterate's negative multiplier is taken as zero in ``H``); each step is a Cholesky solve of
``H`` and a k x k Schur complement. The faces change one at a
time (the coordinate farthest outside the box is fixed, else the face whose multiplier
pushes outwards is released), as in :func:`fastpath.project_cone_box`.
:func:`solve_binding_set` finds the binding set itself: from a start set, the cone most
violated (relative to its tolerance) at the projection joins it, a cone whose multiplier comes
out negative leaves, until no other cone is violated.

The iteration runs compiled only (``afvsgp_gym.cbf._cones``, built with the package when a C
compiler is there, see :mod:`afvsgp_gym._compiled`): without it, or with the backend
``"numpy"``, the filter takes its numpy paths (with one cone
:func:`fastpath.project_cone_box`, the same projection by a secular root, the reference of
:func:`project_cones_box` there; ``docs/filter.md`` says why there is no numpy version of
several cones). The answer is only a candidate:
:class:`~afvsgp_gym.cbf.socp.SOCPFilter` certifies it (:func:`fastpath.certify`).
"""

from __future__ import annotations

import numpy as np

from afvsgp_gym import _compiled

_cones = _compiled.extension("cones")

#: Largest action dimension, binding set and program (cones) the compiled core takes.
MAX_ACTIONS, MAX_CONES, MAX_PROGRAM_CONES = 16, 8, 64
#: The compiled core's return code for an answer with a negative multiplier.
NEGATIVE_MULTIPLIER = -8


def _call(fn, arrays, *rest):
    """``fn(*arrays, *rest)``, the arrays passed as they are (the filter's are C-ordered
    float64) and converted to that when the core refuses them."""
    try:
        return fn(*arrays, *rest)
    except ValueError:
        return fn(*[np.ascontiguousarray(x, dtype=np.float64) for x in arrays], *rest)


def project_cones_box(u_nom, a0, a, G, low, high, u, lam, fixed):
    """``(u, lam)``: the projection of ``u_nom`` onto the cones ``a0_i + a_i u >= ||G_i ubar||``
    (``G`` of shape (k, m+1, m+1)) and the box, every cone binding (module docstring), from
    the point ``u``, the multipliers ``lam`` (k,) and the box faces ``fixed`` (m,) of the
    coordinates held on them. An answer with a negative multiplier is returned too (settled,
    or Newton's iterate after three negative ones running: that cone does not bind, the
    caller drops it). None when it does not settle or ends at a
    cone's apex, or the compiled core is missing or too small for the data."""
    k, m = np.shape(a)
    if _cones is None or m > MAX_ACTIONS or not 1 <= k <= MAX_CONES:
        return None
    u = np.array(u, dtype=np.float64)
    lam = np.array(lam, dtype=np.float64)
    fixed = np.array(fixed, dtype=bool)
    if _call(_cones.project, (u_nom, a0, a, G, low, high), u, lam, fixed) not in (
            0, NEGATIVE_MULTIPLIER):
        return None
    return u, lam


def solve_binding_set(u_nom, a0, a, G, low, high, tol, u, lam, binding, max_binding: int):
    """``(u, lam, binding)``: the projection of ``u_nom`` onto all the cones (``a0`` (K,),
    ``a`` (K, m), ``G`` (K, m+1, m+1)) and the box with the binding set found (module
    docstring), from the point ``u``, the multipliers ``lam`` (K,) and the start set
    ``binding`` (K,) of cones (none: the cone most violated at ``u`` relative to ``tol``);
    at the answer no other cone has a margin below ``-tol`` (K,).
    None when that does not settle, the set would exceed ``max_binding`` cones, or the
    compiled core is missing or too small for the data."""
    K, m = np.shape(a)
    if (_cones is None or m > MAX_ACTIONS or not 1 <= K <= MAX_PROGRAM_CONES
            or not 1 <= max_binding <= MAX_CONES):
        return None
    u = np.array(u, dtype=np.float64)
    lam = np.array(lam, dtype=np.float64)
    binding = np.array(binding, dtype=bool)
    if _call(_cones.solve, (u_nom, a0, a, G, low, high, tol), u, lam, binding,
             int(max_binding)) != 0:
        return None
    return u, lam, binding


def certify_set(u_nom, a0, a, G, low, high, tol, u, lam, binding, dist_tol: float):
    """``(certified, margins)``: :func:`fastpath.certify` of the point ``u`` with the
    multipliers ``lam`` (K,) of the cones ``binding`` (K,) (as :func:`solve_binding_set`
    returns them) for the whole program, compiled; ``margins`` (K,) are the ``c_q(u)``.
    None when the compiled core is missing or too small for the data."""
    K, m = np.shape(a)
    if _cones is None or m > MAX_ACTIONS or K < 1:
        return None
    margins = np.empty(K)
    ok = _call(_cones.certify, (u_nom, a0, a, G, low, high, tol, u, lam),
               np.ascontiguousarray(binding, dtype=bool), margins, float(dist_tol))
    return ok, margins


def cone_margins(u, a0, a, G) -> np.ndarray | None:
    """``a0 + a @ u - ||G ubar||`` (K,) for every cone, compiled; None when the compiled
    core is missing or too small for the data."""
    K, m = np.shape(a)
    if _cones is None or m > MAX_ACTIONS or K < 1:
        return None
    out = np.empty(K)
    _call(_cones.margins, (u, a0, a, G), out)
    return out
