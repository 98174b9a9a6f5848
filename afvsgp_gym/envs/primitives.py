"""Exact signed distance from a safety sphere's centre to obstacle primitives, with the terms
of a relative-degree-2 barrier.

A safety sphere of radius ``r`` with centre ``p`` (velocity ``v``, acceleration ``a``) and a
primitive whose reference point ``c`` (a centre, or a point of a plane) translates with ``c'``,
``c''`` while its orientation stays constant (a rotating primitive would add terms not
modelled here) give the barrier

    (1) h   = d(p_rel) - r,                       p_rel = p - c,  v_rel = v - c'
    (2) h'  = n . v_rel,                          n = grad d (a unit vector)
    (3) h'' = n . (a - c'') + v_rel' H v_rel,     H = the Hessian of d ("curvature")

with ``d`` the primitive's signed distance (negative inside). The kernels
:func:`sphere_distance`, :func:`box_distance`, :func:`capsule_distance` and
:func:`plane_distance` return ``(d, n, curvature = v_rel' H v_rel)`` for K points at once;
:func:`pair_barriers` returns ``(h, h', n, curvature)`` for every (primitive, sphere) pair, in
the form of :func:`afvsgp_gym.envs.scenario.sphere_barriers` (for spheres, its very numbers).

The primitives (world-frame vectors; ``q = R' p_rel`` is a box's own frame):

- Sphere (radius ``R``): ``d = |p_rel| - R``, ``H = (I - n n') / |p_rel|``.
- Plane (unit normal ``m`` through the point; the obstacle lies behind ``m``):
  ``d = m . p_rel``, ``n = m``, ``H = 0``.
- Capsule (unit axis ``t``, half-length ``L``, radius ``R``): with ``s = clip(t . p_rel, -L, L)``
  and ``delta = p_rel - s t`` (from the nearest point of the segment), ``d = |delta| - R``,
  ``H = (I - n n' - t t') / |delta|`` beside the segment (``|t . p_rel| < L``) and
  ``(I - n n') / |delta|`` beyond its ends.
- Box (rotation ``R``, half-sizes ``b``): the faces' signed distances ``f_i = |q_i| - b_i``.
  Outside (some ``f_i > 0``): ``g = max(f, 0)``, ``d = |g|``, ``n = R (sign(q) g) / d`` and
  ``H = R (D - n_q n_q') R' / d`` with ``D = diag(f_i > 0)``: 0 in a face region,
  ``(I - n n' - e e') / d`` in an edge region (``e`` the edge's direction),
  ``(I - n n') / d`` at a corner. Inside (every ``f_i <= 0``): ``d = max_i f_i``, ``n`` the
  normal of that face, ``H = 0``.

What this means for the barrier at relative degree 2:

- The four sets are convex, so ``d`` is a convex function on all of R^3 and ``H`` is positive
  semi-definite wherever it exists: curvature >= 0. (The box and capsule kernels compute it as
  a squared norm, so it is >= 0 in floating point too; the sphere's, by ``sphere_barriers``'
  difference of squares, can round to about -eps |v_rel|^2 / |p_rel|.)
- Outside (``d > 0``) ``d`` is C^1: ``n = (p - proj p) / d`` is continuous, and locally
  Lipschitz since the projection onto a convex set is 1-Lipschitz. ``H`` has one formula per
  region (face, edge, corner; side, end) and jumps where regions meet: crossing a plane
  ``q_i = +-b_i`` (box) or ``t . p_rel = +-L`` (capsule) changes the curvature by
  ``(e . v_rel)^2 / |delta|``, ``e`` that plane's normal, higher on the side with more outside
  axes (edge over face, corner over edge, an end cap over the side). A motion tangent to such
  a plane sees no jump.
- So along any C^2 motion outside the obstacle, ``h`` is C^1 and ``h'`` is locally Lipschitz
  in time: ``h''`` exists for almost every t and equals (3) there (on a boundary with either
  side's ``H``: they agree for the tangent motion that staying on it takes). That is all the
  comparison argument behind a relative-degree-2 (exponential or high-order) CBF uses: with
  ``psi = h' + alpha_1 h`` absolutely continuous, imposing ``psi' + alpha_2 psi >= 0``
  wherever ``h''`` exists keeps ``psi >= 0`` and then ``h >= 0``. It does not need ``h`` to
  be C^2.
- The curvature enters the constraint on the action, ``n . (a - c'') >= -curvature - ...``,
  as a nonnegative term: the admissible accelerations are never fewer than for the plane
  tangent at the closest point (curvature 0), and dropping the term is conservative. With a
  sampled controller that holds (3) over a step, the jump is one caveat: a step that starts in
  an edge or corner region and ends in a face region (or a capsule's cap and ends beside it)
  credits up to ``(e . v_rel)^2 / |delta|`` more curvature than its end has, the same
  one-step discretisation error as any state-dependent term held over a step.
- Inside (``d < 0``, so ``h < -r``) the barrier is already violated; the values there serve
  recovery, not the guarantee. A box's inside distance is that of the nearest face: not
  smooth where two faces tie, ``H = 0`` elsewhere. A sphere's is smooth except at the centre,
  a capsule's except on the segment (``n = 0`` there, as in ``sphere_barriers``) and, as
  outside, ``H`` jumps at its end planes.

Kernels take the geometry as validated by the dataclasses (:class:`Sphere`, :class:`Box`,
:class:`Capsule`, :class:`Plane`), either one set for all K points or one per point; they check
shapes and finiteness of the points only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from afvsgp_gym.envs.scenario import sphere_barriers
from afvsgp_gym.validation import check_finite_array

__all__ = [
    "Box", "Capsule", "Plane", "ShapeStack", "Sphere", "box_distance", "capsule_distance",
    "hessian_stack", "pair_barriers", "pair_barriers_and_hessians", "pair_hessians",
    "plane_distance", "point_distance", "sphere_distance", "stack_shapes",
]

#: Largest ``|R' R - I|`` entry a rotation may have (m of distance error per m of offset).
ORTHONORMAL_TOL = 1e-9

Terms = tuple[np.ndarray, np.ndarray, np.ndarray]


# --- validation --------------------------------------------------------------------------

def _array(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """A read-only float64 copy of ``value``; ValueError unless finite with ``shape``."""
    arr = check_finite_array(value, name, shape)
    arr.flags.writeable = False
    return arr


def _positive(name: str, value, shape: tuple[int, ...] = ()) -> np.ndarray | float:
    arr = _array(name, value, shape)
    if not (arr > 0).all():
        raise ValueError(f"{name} must be > 0, got {arr}")
    return float(arr) if shape == () else arr


def _unit(name: str, value) -> np.ndarray:
    """``value / |value|``; ValueError for a zero vector."""
    arr = _array(name, value, (3,))
    norm = float(np.linalg.norm(arr))
    if not norm > 0:
        raise ValueError(f"{name} must be a non-zero vector, got {arr}")
    unit = arr / norm
    unit.flags.writeable = False
    return unit


def _rotation(name: str, value) -> np.ndarray:
    arr = _array(name, value, (3, 3))
    err = float(np.abs(arr.T @ arr - np.eye(3)).max())
    if err > ORTHONORMAL_TOL or np.linalg.det(arr) < 0:
        raise ValueError(
            f"{name} must be a rotation matrix (orthonormal, det +1; |R'R - I| <= "
            f"{ORTHONORMAL_TOL}), got |R'R - I| = {err:.3g}, det = {np.linalg.det(arr):.6g}"
        )
    return arr


def _points(p_rel, v_rel) -> tuple[np.ndarray, np.ndarray]:
    """``p_rel`` and ``v_rel`` as finite float64 arrays of shape (K, 3)."""
    try:
        shape = np.shape(p_rel)
    except ValueError:  # ragged
        shape = None
    if shape is None or len(shape) != 2 or shape[1] != 3:
        raise ValueError(f"p_rel must have shape (K, 3), got {shape}")
    return _array("p_rel", p_rel, shape), _array("v_rel", v_rel, shape)


def _param(name: str, value, tail: tuple[int, ...], k: int) -> np.ndarray:
    """Geometry for all K points (shape ``tail``) or one per point (``(K, *tail)``)."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != tail and arr.shape != (k, *tail):
        raise ValueError(f"{name} must have shape {tail} or {(k, *tail)}, got {arr.shape}")
    return arr


# --- primitives ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Sphere:
    """Ball of ``radius`` (m) about ``center`` (m)."""

    center: np.ndarray
    radius: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _array("center", self.center, (3,)))
        object.__setattr__(self, "radius", _positive("radius", self.radius))


@dataclass(frozen=True, eq=False)
class Box:
    """Oriented box: ``center`` (m), ``rotation`` (3, 3) whose columns are the box's axes in
    the world, ``half_sizes`` (3,) along them (m)."""

    center: np.ndarray
    rotation: np.ndarray
    half_sizes: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _array("center", self.center, (3,)))
        object.__setattr__(self, "rotation", _rotation("rotation", self.rotation))
        object.__setattr__(self, "half_sizes", _positive("half_sizes", self.half_sizes, (3,)))


@dataclass(frozen=True, eq=False)
class Capsule:
    """The points within ``radius`` (m) of the segment ``center +- half_length * axis``;
    ``axis`` is normalised (a rotation's local z axis is ``R[:, 2]``, as in MuJoCo)."""

    center: np.ndarray
    axis: np.ndarray
    half_length: float
    radius: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _array("center", self.center, (3,)))
        object.__setattr__(self, "axis", _unit("axis", self.axis))
        object.__setattr__(self, "half_length", _positive("half_length", self.half_length))
        object.__setattr__(self, "radius", _positive("radius", self.radius))


@dataclass(frozen=True, eq=False)
class Plane:
    """Half-space ``normal . (x - point) <= 0``: the obstacle lies behind ``normal``
    (normalised)."""

    point: np.ndarray
    normal: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "point", _array("point", self.point, (3,)))
        object.__setattr__(self, "normal", _unit("normal", self.normal))


Primitive = Sphere | Box | Capsule | Plane


# --- kernels: (d, n, curvature) for K points ----------------------------------------------

def _dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", x, y)


def sphere_distance(p_rel, v_rel, radius) -> Terms:
    """Sphere of ``radius`` (scalar or (K,)) about the origin of ``p_rel`` (K, 3): ``d``, ``n``
    and ``v_rel' H v_rel`` by :func:`~afvsgp_gym.envs.scenario.sphere_barriers` itself."""
    p, v = _points(p_rel, v_rel)
    d, _, n, curv = sphere_barriers(p, v, _param("radius", radius, (), len(p)))
    return d, n, curv


def plane_distance(p_rel, v_rel, normal) -> Terms:
    """Half-space behind the unit ``normal`` ((3,) or (K, 3)) through the origin of ``p_rel``:
    ``d = normal . p_rel``, ``n = normal``, curvature 0."""
    p, _ = _points(p_rel, v_rel)
    m = _param("normal", normal, (3,), len(p))
    return _dot(p, m), np.broadcast_to(m, p.shape).copy(), np.zeros(len(p))


def capsule_distance(p_rel, v_rel, axis, half_length, radius) -> Terms:
    """Capsule about the segment ``+- half_length * axis`` through the origin of ``p_rel``
    (geometry per point or shared): ``d = |delta| - radius`` and the module's Hessian."""
    p, v = _points(p_rel, v_rel)
    k = len(p)
    t = _param("axis", axis, (3,), k)
    length = _param("half_length", half_length, (), k)
    s = _dot(p, t)
    delta = p - np.clip(s, -length, length)[:, None] * t
    seg = np.maximum(np.sqrt(_dot(delta, delta)), 1e-9)  # as sphere_barriers: n = 0 on it
    n = delta / seg[:, None]
    side = np.abs(s) < length  # beside the segment: no curvature along t
    # v' H v = |v - (n.v) n - [side] (t.v) t|^2 / |delta|  (n is orthogonal to t beside it)
    perp = v - _dot(n, v)[:, None] * n - np.where(side, _dot(t, v), 0.0)[:, None] * t
    return seg - _param("radius", radius, (), k), n, _dot(perp, perp) / seg


def box_distance(p_rel, v_rel, rotation, half_sizes) -> Terms:
    """Box with axes ``rotation`` ((3, 3) or (K, 3, 3)) and ``half_sizes`` ((3,) or (K, 3))
    about the origin of ``p_rel``: outside, the distance to the closest feature; inside, the
    nearest face's (the module's formulas)."""
    p, v = _points(p_rel, v_rel)
    k = len(p)
    rot = _param("rotation", rotation, (3, 3), k)
    half = _param("half_sizes", half_sizes, (3,), k)
    q = np.einsum("...ji,...j->...i", rot, p)  # R' p_rel: the box's frame
    w = np.einsum("...ji,...j->...i", rot, v)
    face = np.abs(q) - half  # signed distance to each pair of faces' slab
    out = face > 0.0
    sign = np.where(q < 0.0, -1.0, 1.0)
    gap = np.where(out, face, 0.0)
    dist_out = np.sqrt(_dot(gap, gap))
    inside = ~out.any(axis=1)
    safe = np.where(inside, 1.0, dist_out)
    best = np.argmax(face, axis=1)
    nearest_face = sign * (np.arange(3) == best[:, None])
    n_box = np.where(inside[:, None], nearest_face, sign * gap / safe[:, None])
    # v' H v = |D w - (n.w) n|^2 / d, D = diag(out): zero in a face region
    perp = np.where(out, w, 0.0) - _dot(n_box, w)[:, None] * n_box
    curv = np.where(inside, 0.0, _dot(perp, perp) / safe)
    dist = np.where(inside, face.max(axis=1), dist_out)
    return dist, np.einsum("...ij,...j->...i", rot, n_box), curv


def point_distance(shape: Primitive, p_rel) -> float:
    """``d`` of one point ``p_rel`` (3,) (minus the shape's reference point, as the kernels
    take it) in scalar arithmetic: the kernels' distances without their per-call overhead,
    for a figure per step (a reference's clearance), not the barrier terms."""
    p = np.asarray(p_rel, dtype=np.float64)
    if isinstance(shape, Plane):
        return float(shape.normal @ p)
    if isinstance(shape, Capsule):
        s = min(max(float(shape.axis @ p), -shape.half_length), shape.half_length)
        return float(np.linalg.norm(p - s * shape.axis)) - shape.radius
    if isinstance(shape, Box):
        face = np.abs(shape.rotation.T @ p) - shape.half_sizes
        if (face > 0.0).any():
            return float(np.linalg.norm(np.maximum(face, 0.0)))
        return float(face.max())
    return float(np.linalg.norm(p)) - shape.radius


# --- pairs: (h, h', n, curvature) like sphere_barriers ------------------------------------

_FIELDS = {Sphere: ("radius",), Box: ("rotation", "half_sizes"),
           Capsule: ("axis", "half_length", "radius"), Plane: ("normal",)}
_KERNELS = {Sphere: sphere_distance, Box: box_distance, Capsule: capsule_distance,
            Plane: plane_distance}


@dataclass(frozen=True, eq=False)
class ShapeStack:
    """O primitives laid out for S spheres each: row ``k`` of the pair arrays pairs shape
    ``k // S`` with sphere ``k % S`` (the envs' obstacle-major order). ``centers`` (O, 3) are
    the reference points (a plane's ``point``); ``groups`` hold per kind the rows and the
    geometry repeated per row. Build it once with :func:`stack_shapes`."""

    centers: np.ndarray
    n_spheres: int
    groups: tuple[tuple[type, np.ndarray, tuple[np.ndarray, ...]], ...]

    @property
    def n_rows(self) -> int:
        return len(self.centers) * self.n_spheres


def stack_shapes(shapes: Sequence[Primitive], n_spheres: int) -> ShapeStack:
    """Group ``shapes`` by kind for :func:`pair_barriers` with ``n_spheres`` spheres each."""
    if isinstance(shapes, Primitive) or not isinstance(shapes, Sequence) or not shapes:
        raise ValueError("shapes must be a non-empty sequence of Sphere/Box/Capsule/Plane")
    for i, shape in enumerate(shapes):
        if not isinstance(shape, Primitive):
            raise ValueError(f"shapes[{i}] must be a Sphere, Box, Capsule or Plane, got {shape!r}")
    if isinstance(n_spheres, bool) or not isinstance(n_spheres, int | np.integer) or n_spheres < 1:
        raise ValueError(f"n_spheres must be a positive integer, got {n_spheres!r}")
    centers = np.array([s.point if isinstance(s, Plane) else s.center for s in shapes])
    centers.flags.writeable = False
    groups = []
    for kind, fields in _FIELDS.items():
        idx = np.array([i for i, s in enumerate(shapes) if isinstance(s, kind)], dtype=np.intp)
        if idx.size:
            rows = (idx[:, None] * n_spheres + np.arange(n_spheres)).ravel()
            geom = tuple(np.repeat(np.array([getattr(shapes[i], f) for i in idx]), n_spheres,
                                   axis=0) for f in fields)
            groups.append((kind, rows, geom))
    return ShapeStack(centers, int(n_spheres), tuple(groups))


def pair_barriers(
    shapes: ShapeStack | Sequence[Primitive], p_rel, v_rel, radius
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(h, h', n, curvature)`` (eqs. 1-3) of K = O S (shape, sphere) pairs.

    ``p_rel`` (K, 3) = sphere centre minus the shape's reference point (moved: ``c(t)``),
    ``v_rel`` its time derivative, ``radius`` (K,) the sphere's radius; rows in
    :class:`ShapeStack` order (a sequence of O shapes is stacked with S = K / O). Sphere rows
    are :func:`~afvsgp_gym.envs.scenario.sphere_barriers` with radius ``r + R``, bit for bit.
    """
    if not isinstance(shapes, ShapeStack):
        count = len(shapes) if isinstance(shapes, Sequence) and shapes else 1
        rows = np.shape(p_rel)[0] if np.ndim(p_rel) else 0
        shapes = stack_shapes(shapes, max(rows // count, 1))
    p, v = _points(p_rel, v_rel)
    k = shapes.n_rows
    if len(p) != k:
        raise ValueError(f"p_rel must have {k} rows (shapes x spheres), got {len(p)}")
    rad = _array("radius", np.broadcast_to(radius, (k,)) if np.ndim(radius) == 0 else radius,
                 (k,))
    if len(shapes.groups) == 1:  # one kind: no gather or scatter
        kind, _, geom = shapes.groups[0]
        return _group_barriers(kind, p, v, rad, geom)
    h, hd, curv, n = np.empty(k), np.empty(k), np.empty(k), np.empty((k, 3))
    for kind, rows, geom in shapes.groups:
        h[rows], hd[rows], n[rows], curv[rows] = _group_barriers(
            kind, p[rows], v[rows], rad[rows], geom)
    return h, hd, n, curv


def _group_barriers(kind: type, p: np.ndarray, v: np.ndarray, rad: np.ndarray,
                    geom: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    if kind is Sphere:  # h = |d| - (r + R) exactly as the sphere-only envs compute it
        return sphere_barriers(p, v, rad + geom[0])
    d, n, curv = _KERNELS[kind](p, v, *geom)
    return d - rad, _dot(n, v), n, curv


# --- Hessians: H of every pair, from the kernels' curvature -------------------------------

#: The directions whose curvatures ``u' H u`` give the six entries of a symmetric ``H``:
#: ``H_ii = c(e_i)`` and ``H_ij = (c(e_i + e_j) - c(e_i) - c(e_j)) / 2``.
_POLARISATION = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0],
                          [1.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])
#: Rows per pair in a :func:`hessian_stack`: the pair's own, then one per direction.
_HESSIAN_ROWS = 1 + len(_POLARISATION)


def hessian_stack(shapes: Sequence[Primitive], n_spheres: int) -> ShapeStack:
    """The stack :func:`pair_barriers_and_hessians` and :func:`pair_hessians` take for
    ``shapes`` with ``n_spheres`` spheres each (the pair's own row and one per direction of
    the polarisation; build it once)."""
    if isinstance(n_spheres, bool) or not isinstance(n_spheres, int | np.integer) or n_spheres < 1:
        raise ValueError(f"n_spheres must be a positive integer, got {n_spheres!r}")
    return stack_shapes(shapes, _HESSIAN_ROWS * int(n_spheres))


def pair_barriers_and_hessians(
    stack: ShapeStack, p_rel, v_rel, radius
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`pair_barriers`' ``(h, h', n, curvature)`` of the K = O S pairs and ``H``
    (K, 3, 3), the Hessian of the signed distance at every ``p_rel``, in one pass of the
    kernels (``stack``: :func:`hessian_stack` of the O shapes and S spheres).

    ``H`` comes from the kernels' own curvature by polarisation: at a fixed point ``v' H v``
    is a quadratic form in ``v`` (the module's formulas; the region, and so ``H``, depends on
    the point only), so its values at six directions give ``H`` to rounding. 0 where ``H``
    is (faces, planes, inside a box)."""
    n_dir = len(_POLARISATION)
    if not isinstance(stack, ShapeStack) or stack.n_spheres % _HESSIAN_ROWS:
        raise ValueError("stack must be hessian_stack(shapes, n_spheres)")
    o, s = len(stack.centers), stack.n_spheres // _HESSIAN_ROWS
    p, v = _points(p_rel, v_rel)
    if len(p) != o * s:
        raise ValueError(f"p_rel must have {o * s} rows (shapes x spheres), got {len(p)}")
    rows = np.empty((o, _HESSIAN_ROWS, s, 3))
    rows[:] = p.reshape(o, 1, s, 3)
    dirs = np.empty((o, _HESSIAN_ROWS, s, 3))
    dirs[:, 0] = v.reshape(o, s, 3)
    dirs[:, 1:] = _POLARISATION[None, :, None, :]
    rad = np.ones((o, _HESSIAN_ROWS, s))  # (the directions' rows: any radius, H has none)
    rad[:, 0] = np.broadcast_to(radius, (o * s,)).reshape(o, s)
    h, hd, n, curv = pair_barriers(stack, rows.reshape(-1, 3), dirs.reshape(-1, 3),
                                   rad.reshape(-1))
    own = np.zeros((o, _HESSIAN_ROWS, s), dtype=bool)
    own[:, 0] = True
    own = own.ravel()
    c = curv.reshape(o, _HESSIAN_ROWS, s)[:, 1:].transpose(0, 2, 1).reshape(o * s, n_dir)
    hess = np.empty((o * s, 3, 3))
    hess[:, [0, 1, 2], [0, 1, 2]] = c[:, :3]
    for col, (i, j) in enumerate(((0, 1), (0, 2), (1, 2)), start=3):
        hess[:, i, j] = hess[:, j, i] = 0.5 * (c[:, col] - c[:, i] - c[:, j])
    return h[own], hd[own], n[own], curv[own], hess


def pair_hessians(stack: ShapeStack, p_rel) -> np.ndarray:
    """``H`` (K, 3, 3) of :func:`pair_barriers_and_hessians` alone."""
    p = np.asarray(p_rel, dtype=np.float64)
    return pair_barriers_and_hessians(stack, p, np.zeros(np.shape(p)), 1.0)[4]
