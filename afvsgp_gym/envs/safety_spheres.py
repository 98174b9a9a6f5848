"""Safety spheres: the robot geometry the barriers protect, as data.

A safety sphere is fixed to one body of the robot: ``(body, offset, radius)`` with ``offset``
in the body frame (m). Each (sphere, obstacle) pair is one barrier
``h = |p_s - p_obs| - (r_s + r_obs)``.

``PANDA_ARM_SPHERES`` covers every moving link of the gymnasium-robotics Panda (links 1-7,
the hand and the fingers, which are rigid here): fitted to the collision meshes (convex hulls)
and finger primitives of that model, surface points included, by clustering and a minimal
enclosing ball per cluster (``benchmarks/fit_safety_spheres.py`` regenerates the numbers).
Every surface point of those collision geoms lies inside the union up to
:data:`COVERAGE_TOLERANCE` (tests/envs check every mesh vertex and points on the finger
primitives, and that ``mj_geomDistance`` from the collision geoms to sphere, box, capsule and
plane obstacles is at least the smallest barrier ``h`` less it).

The base (link0) does not move and has no obstacle barrier. ``PANDA_BASE_SPHERES``, fitted to
its collision mesh the same way and held to the same tolerance, serve the self-collision
barriers only (:mod:`~afvsgp_gym.envs.self_collision`): the sphere sets of
``safety_spheres`` never include them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["COVERAGE_TOLERANCE", "PANDA_ARM_SPHERES", "PANDA_BASE_SPHERES", "SafetySphere",
           "end_effector_sphere", "parse_spheres"]

#: How far (m) a point of the arm's collision geoms may lie outside the union of
#: :data:`PANDA_ARM_SPHERES` (the fit misses by millimetres at most, on the finger
#: primitives), and a point of the base's outside :data:`PANDA_BASE_SPHERES`: a distance
#: from the geoms is at least the spheres' less this.
COVERAGE_TOLERANCE = 0.01


@dataclass(frozen=True)
class SafetySphere:
    """A sphere of ``radius`` (m) at ``offset`` (m, body frame) on the body named ``body``."""

    body: str
    offset: tuple[float, float, float]
    radius: float


def _s(body: str, x: float, y: float, z: float, r: float) -> SafetySphere:
    return SafetySphere(f"panda0_{body}", (x, y, z), r)


#: Whole-arm sphere set of the gymnasium-robotics Panda (21 spheres, see the module docstring).
PANDA_ARM_SPHERES: tuple[SafetySphere, ...] = (
    _s("link1", 0.0014, -0.0106, -0.1294, 0.0908),
    _s("link1", -0.0001, -0.0482, -0.0192, 0.0889),
    _s("link2", 0.0007, -0.1296, 0.0097, 0.0914),
    _s("link2", -0.0002, -0.0198, 0.0484, 0.0890),
    _s("link3", 0.0732, 0.0393, -0.0104, 0.0806),
    _s("link3", 0.0098, 0.0047, -0.0701, 0.0834),
    _s("link4", -0.0097, 0.0107, 0.0388, 0.0813),
    _s("link4", -0.0724, 0.0728, 0.0041, 0.0835),
    _s("link5", 0.0002, 0.0064, -0.2151, 0.0756),
    _s("link5", 0.0032, 0.0155, -0.0200, 0.0739),
    _s("link5", -0.0004, 0.0451, -0.1304, 0.0840),
    _s("link5", -0.0006, 0.0755, -0.0186, 0.0744),
    _s("link6", 0.0831, 0.0092, -0.0002, 0.0779),
    _s("link6", 0.0170, 0.0047, 0.0054, 0.0691),
    # link7 with the hand and the (rigid) fingers, in the link7 frame
    _s("link7", -0.0012, -0.0013, 0.0772, 0.0515),
    _s("link7", 0.0321, 0.0327, 0.0801, 0.0542),
    _s("link7", -0.0501, -0.0482, 0.1295, 0.0509),
    _s("link7", 0.0473, 0.0468, 0.1388, 0.0449),
    _s("link7", -0.0023, -0.0021, 0.1492, 0.0501),
    _s("link7", -0.0000, -0.0000, 0.2039, 0.0320),
    _s("link7", -0.0001, 0.0003, 0.2395, 0.0255),
)

#: The base's (link0's) spheres, in the link0 frame: for the self-collision barriers only
#: (see the module docstring).
PANDA_BASE_SPHERES: tuple[SafetySphere, ...] = (
    _s("link0", -0.0717, -0.0009, 0.0039, 0.0929),
    _s("link0", -0.0001, -0.0001, 0.0489, 0.1066),
)


def end_effector_sphere(radius: float) -> SafetySphere:
    """The paper's single sphere around the end-effector site (link7, 0.21 m along its axis)."""
    return SafetySphere("panda0_link7", (0.0, 0.0, 0.21), float(radius))


def parse_spheres(spheres: Sequence, body_names: Sequence[str]) -> tuple[SafetySphere, ...]:
    """Validate a user sphere list: SafetySphere, ``(body, offset, radius)`` or a dict with
    those keys. ``ValueError`` names the bad entry (unknown body, radius not > 0, NaN)."""
    if isinstance(spheres, (str, Mapping)) or not isinstance(spheres, Sequence) or not spheres:
        raise ValueError(
            "safety_spheres must be 'arm', 'ee' or a non-empty list of (body, offset, radius)"
        )
    known = set(body_names)
    out = []
    for i, entry in enumerate(spheres):
        try:
            if isinstance(entry, SafetySphere):
                body, offset, radius = entry.body, entry.offset, entry.radius
            elif isinstance(entry, Mapping):
                extra = set(entry) - {"body", "offset", "radius"}
                if extra:
                    raise ValueError(f"unknown keys {sorted(extra)}")
                body, offset, radius = entry["body"], entry["offset"], entry["radius"]
            else:
                body, offset, radius = entry
            offset = tuple(float(x) for x in offset)
            radius = float(radius)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(
                f"safety_spheres[{i}] = {entry!r} must be (body, (x, y, z), radius): {exc}"
            ) from None
        if body not in known:
            raise ValueError(
                f"safety_spheres[{i}]: unknown body {body!r}; valid: {sorted(known)}"
            )
        if len(offset) != 3 or not all(math.isfinite(x) for x in offset):
            raise ValueError(f"safety_spheres[{i}]: offset must be 3 finite numbers, got {offset}")
        if not (math.isfinite(radius) and radius > 0):
            raise ValueError(f"safety_spheres[{i}]: radius must be > 0, got {radius}")
        out.append(SafetySphere(str(body), offset, radius))
    return tuple(out)


def sphere_arrays(spheres: Sequence[SafetySphere]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """``(bodies, offsets (S, 3), radii (S,))`` of a sphere list."""
    return (
        [s.body for s in spheres],
        np.array([s.offset for s in spheres], dtype=np.float64).reshape(-1, 3),
        np.array([s.radius for s in spheres], dtype=np.float64),
    )
