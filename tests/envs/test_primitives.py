"""Obstacle primitives: d, n and the curvature against finite differences, independent
formulas and MuJoCo's mj_geomDistance; the sphere path is sphere_barriers bit for bit; bad input
is refused by name."""

import re

import mujoco
import numpy as np
import pytest

from afvsgp_gym.envs import primitives as pr
from afvsgp_gym.envs.scenario import sphere_barriers

EPS = np.finfo(np.float64).eps
#: The O(1) constant of the error models below (Taylor remainders, a few roundings), fixed
#: from the models, not fitted: the measured errors are at most 0.1 of these bounds.
SAFETY = 10.0
#: Points closer than this (m) to a boundary between regions are left out of the finite
#: differences: there H (or, inside a box, n) jumps, so a stencil reaching across measures a
#: mix of both sides, and shrinking the step to fit leaves rounding in charge.
MIN_MARGIN = 0.02

CASES = [("sphere", "outside"), ("sphere", "inside"), ("box", "face"), ("box", "edge"),
         ("box", "corner"), ("box", "inside"), ("capsule", "side"), ("capsule", "end"),
         ("capsule", "inside"), ("plane", "front"), ("plane", "behind")]


def _rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _units(rng, n):
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def _sample(kind, region, rng, n=80):
    """A primitive at a random pose and ``n`` points ``p_rel`` (world axes, from its reference
    point) in ``region``, each with its margin to the nearest boundary between regions (inf
    if none) and its length scale: the smaller of that margin and the curvature radius (the
    distance to the sphere's centre, the capsule's segment, the box)."""
    center = rng.uniform(-1, 1, 3)
    if kind == "sphere":
        radius = rng.uniform(0.1, 0.5)
        lo, hi = (radius + 0.02, radius + 0.6) if region == "outside" else (0.1 * radius,
                                                                              0.9 * radius)
        rho = rng.uniform(lo, hi, n)
        return pr.Sphere(center, radius), rho[:, None] * _units(rng, n), rho, np.full(n, np.inf)
    if kind == "plane":
        normal = _units(rng, 1)[0]
        side = 1.0 if region == "front" else -1.0
        lateral = rng.uniform(-1, 1, (n, 3))
        lateral -= (lateral @ normal)[:, None] * normal
        p = side * rng.uniform(0.02, 1.0, n)[:, None] * normal + lateral
        return pr.Plane(center, normal), p, np.ones(n), np.full(n, np.inf)  # flat: 1 m
    rot = _rotation(rng)
    if kind == "box":
        half = rng.uniform(0.1, 0.5, 3)
        n_out = {"inside": 0, "face": 1, "edge": 2, "corner": 3}[region]
        q = rng.uniform(-1, 1, (n, 3)) * half
        if not n_out:  # nearest face i at depth t, the others' deeper by 2 MIN_MARGIN or more
            depth = rng.uniform(0.03, 0.7 * half.min(), n)
            q = rng.uniform(-1, 1, (n, 3)) * np.maximum(half - depth[:, None] - 0.05, 0.0)
            i = rng.integers(0, 3, n)
            q[np.arange(n), i] = rng.choice([-1.0, 1.0], n) * (half[i] - depth)
        for row in q:
            axes = rng.permutation(3)[:n_out]
            row[axes] = rng.choice([-1.0, 1.0], n_out) * (half[axes] + rng.uniform(0.02, 0.5,
                                                                                  n_out))
        face = np.abs(q) - half
        if n_out:
            radius = np.linalg.norm(np.maximum(face, 0.0), axis=1)
            margin = np.abs(face).min(axis=1)
        else:  # n jumps where two faces tie and where the nearest face's q_i changes sign
            top = np.sort(face, axis=1)
            radius = np.full(n, np.inf)
            q_best = np.abs(q[np.arange(n), np.argmax(face, axis=1)])
            margin = np.minimum.reduce([-top[:, 2], (top[:, 2] - top[:, 1]) / 2, q_best])
        return pr.Box(center, rot, half), q @ rot.T, np.minimum(radius, margin), margin
    length, radius = rng.uniform(0.1, 0.5), rng.uniform(0.05, 0.3)
    axis = rot[:, 2]
    if region == "inside":
        rho = rng.uniform(0.1, 0.9, n) * radius
    else:
        rho = radius + rng.uniform(0.02, 0.6, n)
    end = rng.random(n) < 0.5 if region == "inside" else np.full(n, region == "end")
    sign = rng.choice([-1.0, 1.0], n)
    # beside: a radial direction at z within the segment; beyond an end: a direction out of it
    angle = rng.uniform(0, 2 * np.pi, n)
    radial = np.cos(angle)[:, None] * rot[:, 0] + np.sin(angle)[:, None] * rot[:, 1]
    out = _units(rng, n)
    out += (sign * (np.abs(out @ axis) + 0.2) - out @ axis)[:, None] * axis
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    z = np.where(end, sign * length, rng.uniform(-1, 1, n) * length)
    p = z[:, None] * axis + rho[:, None] * np.where(end[:, None], out, radial)
    margin = np.abs(np.abs(p @ axis) - length)
    return pr.Capsule(center, axis, length, radius), p, np.minimum(rho, margin), margin


def _kernel(shape):
    """``(p_rel, v_rel) -> (d, n, curvature)`` of ``shape``'s kind."""
    if isinstance(shape, pr.Sphere):
        return lambda p, v: pr.sphere_distance(p, v, shape.radius)
    if isinstance(shape, pr.Box):
        return lambda p, v: pr.box_distance(p, v, shape.rotation, shape.half_sizes)
    if isinstance(shape, pr.Capsule):
        return lambda p, v: pr.capsule_distance(p, v, shape.axis, shape.half_length,
                                                shape.radius)
    return lambda p, v: pr.plane_distance(p, v, shape.normal)


def _size(shape):
    return float(sum(np.sum(np.abs(getattr(shape, f))) for f in ("radius", "half_sizes",
                                                                   "half_length")
                     if hasattr(shape, f)))


def _away_from_boundaries(p, ell, margin):
    """The points at least MIN_MARGIN from a region boundary (see MIN_MARGIN: why)."""
    keep = margin >= MIN_MARGIN
    assert keep.sum() >= len(p) // 5, "too few points away from region boundaries"
    return p[keep], ell[keep]


@pytest.mark.parametrize("kind, region", CASES)
def test_normal_is_the_gradient_of_d(kind, region):
    """Central differences of d: step h = eps^(1/3) l, error h^2 |d'''| + eps S / h with
    |d'''| ~ 1 / l^2 and S the magnitude the kernel rounds at, so
    |n_fd - n| <= eps^(2/3) (1 + S / l) up to SAFETY."""
    rng = np.random.default_rng(CASES.index((kind, region)))
    shape, p, ell, margin = _sample(kind, region, rng)
    p, ell = _away_from_boundaries(p, ell, margin)
    f = _kernel(shape)
    d, n, _ = f(p, np.zeros_like(p))
    step = EPS ** (1 / 3) * ell
    n_fd = np.empty_like(p)
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1.0
        hi = f(p + step[:, None] * e, np.zeros_like(p))[0]
        lo = f(p - step[:, None] * e, np.zeros_like(p))[0]
        n_fd[:, j] = (hi - lo) / (2 * step)
    scale = np.linalg.norm(p, axis=1) + _size(shape)
    tol = SAFETY * EPS ** (2 / 3) * (1 + scale / ell)
    assert np.all(np.abs(n_fd - n).max(axis=1) <= tol)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=0, atol=4 * EPS)
    assert np.all((d > 0) == (region in ("outside", "face", "edge", "corner", "side", "end",
                                         "front")))


@pytest.mark.parametrize("moving", [False, True], ids=["static", "moving"])
@pytest.mark.parametrize("kind, region", CASES)
def test_curvature_is_the_second_time_derivative(kind, region, moving):
    """h'' = n . (a - c'') + v_rel' H v_rel (eq. 3) along p(t) = p0 + v t + a t^2 / 2 with the
    primitive at c(t) = c0 + c' t + c'' t^2 / 2.

    Time scale T = min(l / |v_rel|, sqrt(l / |a_rel|)), so every derivative of d(p_rel(t)) of
    order k is ~ l / T^k, and rounding is eps S. Two checks: the second difference of d
    (step eps^(1/4) T, error ~ sqrt(eps) (l + S) / T^2) and the first difference of the
    analytic h' = n . v_rel (step eps^(1/3) T, error ~ eps^(2/3) (l + S) / T^2)."""
    rng = np.random.default_rng(100 + CASES.index((kind, region)) + 50 * moving)
    shape, p_rel, ell, margin = _sample(kind, region, rng)
    p_rel, ell = _away_from_boundaries(p_rel, ell, margin)
    k = len(p_rel)
    c0 = pr.stack_shapes([shape], 1).centers[0]
    cv, ca = (rng.normal(size=3), rng.normal(size=3)) if moving else (np.zeros(3),) * 2
    p0, v, a = c0 + p_rel, rng.normal(size=(k, 3)), rng.normal(size=(k, 3))
    v_rel, a_rel = v - cv, a - ca
    f = _kernel(shape)

    def rel(t):
        t = t[:, None]
        return (p0 + v * t + a * t * t / 2) - (c0 + cv * t + ca * t * t / 2), v_rel + a_rel * t

    d, n, curv = f(p_rel, v_rel)
    h2 = np.einsum("ki,ki->k", n, a_rel) + curv
    t_scale = np.minimum(ell / np.linalg.norm(v_rel, axis=1),
                         np.sqrt(ell / np.linalg.norm(a_rel, axis=1)))
    scale = np.linalg.norm(p0, axis=1) + np.linalg.norm(c0) + _size(shape) + ell
    unit = scale / t_scale**2

    tau = EPS ** 0.25 * t_scale
    second = (f(*rel(tau))[0] - 2 * f(*rel(0 * tau))[0] + f(*rel(-tau))[0]) / tau**2
    assert np.all(np.abs(second - h2) <= SAFETY * np.sqrt(EPS) * unit)

    tau = EPS ** (1 / 3) * t_scale

    def h1(t):
        q, w = rel(t)
        return np.einsum("ki,ki->k", f(q, w)[1], w)

    first = (h1(tau) - h1(-tau)) / (2 * tau)
    assert np.all(np.abs(first - h2) <= SAFETY * EPS ** (2 / 3) * unit)

    # the same through pair_barriers with the sphere's radius: h = d - r, h' = n . v_rel
    h, hd, n2, curv2 = pr.pair_barriers([shape], p_rel, v_rel, 0.05)
    np.testing.assert_array_equal(n2, n)
    np.testing.assert_array_equal(curv2, curv)
    if kind != "sphere":  # a sphere's h is |d| - (r + R): equal to rounding, not bit for bit
        np.testing.assert_array_equal(h, d - 0.05)
    np.testing.assert_allclose(h, d - 0.05, rtol=0, atol=4 * EPS * scale.max())
    np.testing.assert_allclose(hd, np.einsum("ki,ki->k", n, v_rel), rtol=0, atol=0)


@pytest.mark.parametrize("kind", ["box", "capsule"])
def test_curvature_is_nonnegative_and_jumps_as_documented(kind):
    """d is convex, so v' H v >= 0; across a region boundary n is continuous and the
    curvature jumps by (e . v)^2 / dist, e the boundary plane's normal (module docstring)."""
    rng = np.random.default_rng(7)
    for region in (("face", "edge", "corner", "inside") if kind == "box"
                   else ("side", "end", "inside")):
        shape, p, _, _ = _sample(kind, region, rng)
        assert np.all(_kernel(shape)(p, rng.normal(size=p.shape))[2] >= 0.0)
    rot = _rotation(rng)
    v = rng.normal(size=(1, 3))
    gap = 1e-12  # either side of the boundary plane
    if kind == "box":  # face region (x) meets the edge region (x, y) at q_y = b_y
        half = np.array([0.2, 0.3, 0.4])
        shape, e, dist = pr.Box(np.zeros(3), rot, half), rot[:, 1], 0.25
        q = np.array([half[0] + dist, half[1], 0.1])
    else:  # the side meets the end cap at q_z = L
        shape, e, dist = pr.Capsule(np.zeros(3), rot[:, 2], 0.3, 0.1), rot[:, 2], 0.25
        q = np.array([dist, 0.0, 0.3])
    f = _kernel(shape)
    below, above = ((q - gap * s * np.eye(3)[1 if kind == "box" else 2]) @ rot.T
                    for s in (1, -1))
    _, n_lo, k_lo = f(below[None], v)
    _, n_hi, k_hi = f(above[None], v)
    err = SAFETY * (EPS * (np.linalg.norm(q) + 1.0) + gap) / dist  # rounding + the step
    np.testing.assert_allclose(n_hi, n_lo, rtol=0, atol=err)
    np.testing.assert_allclose(k_hi - k_lo, (v @ e) ** 2 / dist, rtol=0,
                               atol=err * float(np.sum(v * v)) / dist)


def _segment_distance(p, a, b):
    """Distance from points p (N, 3) to the segment ab: an end when the angle there is obtuse,
    else the triangle's height |(b - a) x (p - a)| / |b - a| (no projection, no clipping)."""
    ab = b - a
    height = np.linalg.norm(np.cross(ab, p - a), axis=1) / np.linalg.norm(ab)
    to_a, to_b = np.linalg.norm(p - a, axis=1), np.linalg.norm(p - b, axis=1)
    return np.where((p - a) @ ab <= 0, to_a, np.where((p - b) @ -ab <= 0, to_b, height))


def _box_distance_by_features(box, p):
    """Signed distance to ``box`` from its 6 faces, 12 edges and 8 corners in world
    coordinates: the nearest feature's distance, negative when behind all 6 face planes."""
    c, rot, half = box.center, box.rotation, box.half_sizes
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    corners = c + (signs * half) @ rot.T
    best = np.min([np.linalg.norm(p - x, axis=1) for x in corners], axis=0)
    for i in range(8):
        for j in range(i + 1, 8):
            if np.sum(signs[i] != signs[j]) == 1:
                best = np.minimum(best, _segment_distance(p, corners[i], corners[j]))
    behind = np.ones(len(p), dtype=bool)
    for axis in range(3):
        for s in (-1.0, 1.0):
            normal = s * rot[:, axis]
            height = (p - (c + half[axis] * normal)) @ normal
            behind &= height <= 0
            others = [o for o in range(3) if o != axis]
            on_face = np.all(np.abs((p - c) @ rot[:, others]) <= half[others], axis=1)
            best = np.where(on_face, np.minimum(best, np.abs(height)), best)
    return np.where(behind, -best, best)


def test_box_and_capsule_distance_match_independent_formulas():
    """Both computations are a few float64 operations on numbers of size S: they agree to
    64 eps S (at most; measured: <= 0.55 eps S)."""
    rng = np.random.default_rng(11)
    for region in ("face", "edge", "corner", "inside"):
        box, p, _, _ = _sample("box", region, rng, n=200)
        d = pr.box_distance(p, np.zeros_like(p), box.rotation, box.half_sizes)[0]
        world = box.center + p
        scale = np.linalg.norm(world, axis=1).max() + np.linalg.norm(box.center) + 1.0
        np.testing.assert_allclose(d, _box_distance_by_features(box, world), rtol=0,
                                   atol=64 * EPS * scale)
    for region in ("side", "end", "inside"):
        cap, p, _, _ = _sample("capsule", region, rng, n=200)
        d = pr.capsule_distance(p, np.zeros_like(p), cap.axis, cap.half_length, cap.radius)[0]
        ends = (-cap.half_length * cap.axis, cap.half_length * cap.axis)
        scale = np.linalg.norm(p, axis=1).max() + 1.0
        np.testing.assert_allclose(d, _segment_distance(p, *ends) - cap.radius, rtol=0,
                                   atol=64 * EPS * scale)


@pytest.mark.parametrize("kind, region", CASES)
def test_point_distance_is_the_kernels_distance(kind, region):
    """The scalar one-point distance agrees with pair_barriers' (rounding: other sums)."""
    shape, p, _, _ = _sample(kind, region, np.random.default_rng(5), n=40)
    d = pr.pair_barriers([shape], p, np.zeros_like(p), 0.0)[0]
    scale = np.linalg.norm(p, axis=1).max() + 1.0
    np.testing.assert_allclose([pr.point_distance(shape, x) for x in p], d, rtol=0,
                               atol=64 * EPS * scale)


_GEOMS = """<mujoco><worldbody>
  <geom type="sphere" size="{r}"/>
  <geom type="box" size="{b[0]} {b[1]} {b[2]}"/>
  <geom type="capsule" size="{cr} {cl}"/>
  <geom type="plane" size="1 1 1"/>
</worldbody></mujoco>"""


@pytest.mark.skipif(not hasattr(mujoco, "mj_geomDistance"),
                    reason="mujoco.mj_geomDistance needs a newer MuJoCo")
def test_distance_matches_mujoco_geom_distance():
    """h = d(p) - r against MuJoCo's signed sphere-geom distance. MuJoCo computes these
    three pairs in closed form (no convex solver, no tolerance), so both are float64 formulas
    on numbers of size S: agreement within 64 eps S (measured: <= 0.7 eps S, 3e-16 m, on
    MuJoCo 3.3.6 and 4.0.1).
    Placements: mostly apart, some overlapping, some with the centre inside."""
    rng = np.random.default_rng(5)
    worst, counts = 0.0, {"apart": 0, "overlap": 0}
    for _ in range(3):
        r, half = rng.uniform(0.05, 0.2), rng.uniform(0.05, 0.4, 3)
        cap_r, cap_l = rng.uniform(0.05, 0.3), rng.uniform(0.05, 0.4)
        model = mujoco.MjModel.from_xml_string(_GEOMS.format(r=r, b=half, cr=cap_r, cl=cap_l))
        data = mujoco.MjData(model)
        for _ in range(100):
            p = rng.uniform(-0.8, 0.8, 3)
            rots = [_rotation(rng) for _ in range(3)]
            centers = rng.uniform(-0.1, 0.1, (3, 3))
            data.geom_xpos[0] = p  # geom poses written where the collision code reads them
            data.geom_xmat[0] = np.eye(3).ravel()
            for g in range(3):
                data.geom_xpos[g + 1] = centers[g]
                data.geom_xmat[g + 1] = rots[g].ravel()
            shapes = [pr.Box(centers[0], rots[0], half),
                      pr.Capsule(centers[1], rots[1][:, 2], cap_l, cap_r),
                      pr.Plane(centers[2], rots[2][:, 2])]
            h = pr.pair_barriers(shapes, p - centers, np.zeros((3, 3)), r)[0]
            ref = np.array([mujoco.mj_geomDistance(model, data, 0, g, 10.0, None)
                            for g in (1, 2, 3)])
            scale = np.linalg.norm(p) + np.linalg.norm(centers, axis=1) + 1.0
            worst = max(worst, float(np.max(np.abs(h - ref) / (EPS * scale))))
            counts["apart"] += int(np.sum(ref > 0))
            counts["overlap"] += int(np.sum(ref <= 0))
    assert min(counts.values()) >= 50, counts
    assert worst <= 64, worst


def test_sphere_path_is_sphere_barriers_bit_for_bit():
    """Sphere rows give the numbers the sphere-only envs compute today, in the envs' layout
    (obstacle-major, radii r_o + r_s), whether the stack holds spheres only or mixed kinds."""
    rng = np.random.default_rng(3)
    n_s = 5
    spheres = [pr.Sphere(rng.normal(size=3), r) for r in rng.uniform(0.05, 0.3, 4)]
    r_s = rng.uniform(0.02, 0.1, n_s)
    d, vr = rng.normal(size=(4 * n_s, 3)), rng.normal(size=(4 * n_s, 3))
    rad = (np.array([s.radius for s in spheres])[:, None] + r_s[None, :]).ravel()
    ref = sphere_barriers(d, vr, rad)
    for got, want in zip(pr.pair_barriers(spheres, d, vr, np.tile(r_s, 4)), ref, strict=True):
        np.testing.assert_array_equal(got, want)
    mixed = [spheres[0], pr.Plane(np.zeros(3), [0, 0, 1]), spheres[2],
             pr.Box(np.zeros(3), np.eye(3), [0.1, 0.2, 0.3])]
    stack = pr.stack_shapes(mixed, n_s)
    rows = np.r_[0:n_s, 2 * n_s:3 * n_s]
    for got, want in zip(pr.pair_barriers(stack, d, vr, np.tile(r_s, 4)), ref, strict=True):
        np.testing.assert_array_equal(got[rows], want[rows])
    h, _, n, curv = sphere_barriers(d, vr, 0.2)
    for got, want in zip(pr.sphere_distance(d, vr, 0.2), (h, n, curv), strict=True):
        np.testing.assert_array_equal(got, want)


def _p():
    return np.zeros((2, 3))


BAD = [
    ("center", lambda: pr.Sphere([0, 0], 1.0)),
    ("center", lambda: pr.Sphere([0, 0, np.nan], 1.0)),
    ("radius", lambda: pr.Sphere([0, 0, 0], 0.0)),
    ("radius", lambda: pr.Sphere([0, 0, 0], np.inf)),
    ("rotation", lambda: pr.Box([0, 0, 0], 1.01 * np.eye(3), [1, 1, 1])),
    ("rotation", lambda: pr.Box([0, 0, 0], np.diag([1.0, 1.0, -1.0]), [1, 1, 1])),
    ("rotation", lambda: pr.Box([0, 0, 0], np.eye(3)[:, :2], [1, 1, 1])),
    ("half_sizes", lambda: pr.Box([0, 0, 0], np.eye(3), [0.1, 0.0, 0.1])),
    ("half_sizes", lambda: pr.Box([0, 0, 0], np.eye(3), [0.1, 0.1])),
    ("axis", lambda: pr.Capsule([0, 0, 0], [0, 0, 0], 0.3, 0.1)),
    ("half_length", lambda: pr.Capsule([0, 0, 0], [0, 0, 1], -0.3, 0.1)),
    ("radius", lambda: pr.Capsule([0, 0, 0], [0, 0, 1], 0.3, "wide")),
    ("normal", lambda: pr.Plane([0, 0, 0], [0, 0, 0])),
    ("point", lambda: pr.Plane([0, 0], [0, 0, 1])),
    ("p_rel", lambda: pr.box_distance(np.zeros((2, 2)), np.zeros((2, 2)), np.eye(3), [1] * 3)),
    ("p_rel", lambda: pr.plane_distance(np.full((2, 3), np.nan), _p(), [0, 0, 1])),
    ("p_rel", lambda: pr.sphere_distance([[0, 0, 0], [0, 0]], _p(), 1.0)),
    ("v_rel", lambda: pr.capsule_distance(_p(), np.zeros((3, 3)), [0, 0, 1], 0.3, 0.1)),
    ("rotation", lambda: pr.box_distance(_p(), _p(), np.eye(2), [1, 1, 1])),
    ("half_sizes", lambda: pr.box_distance(_p(), _p(), np.eye(3), np.ones((3, 3)))),
    ("shapes", lambda: pr.stack_shapes([], 1)),
    ("shapes[1]", lambda: pr.stack_shapes([pr.Sphere([0, 0, 0], 1.0), object()], 1)),
    ("n_spheres", lambda: pr.stack_shapes([pr.Sphere([0, 0, 0], 1.0)], 0)),
    ("p_rel", lambda: pr.pair_barriers([pr.Sphere([0, 0, 0], 1.0)] * 2, np.zeros((3, 3)),
                                       np.zeros((3, 3)), 0.1)),
    ("radius", lambda: pr.pair_barriers([pr.Sphere([0, 0, 0], 1.0)], _p(), _p(), [0.1] * 3)),
    ("radius", lambda: pr.pair_barriers([pr.Sphere([0, 0, 0], 1.0)], _p(), _p(), np.nan)),
]


@pytest.mark.parametrize("name, call", BAD, ids=[f"{i}-{b[0]}" for i, b in enumerate(BAD)])
def test_bad_input_is_refused_by_name(name, call):
    with pytest.raises(ValueError, match="^" + re.escape(name) + " "):
        call()
