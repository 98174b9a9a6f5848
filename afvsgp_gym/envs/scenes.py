"""Franka scenes of several typed obstacles: a cluttered tabletop and a shelf.

Geometry only (numpy, no MuJoCo): each function returns the scene's
:class:`~afvsgp_gym.envs.scenario.ObstacleSpec` list in a fixed order of kinds, so the
number of obstacles (and of barriers) is the same at every reset. Positions are relative
to the reference centre ``c`` (the end-effector at the ready pose, about (0.307, 0, 0.487) m).

Where the arm goes: the tracker of the y reference (+-0.28 m about ``c``, hand down) sweeps
its safety spheres through ``x`` in [-0.25, 0.43] m, ``y`` in [-0.37, 0.41] m above
``z`` = 0.395 m, and through the column of radius 0.2 m about the base below (measured over a
full cycle). :data:`ARM_SWEEP` is that volume grown by a margin; the clutter is drawn outside
it, near the path but off it.
"""

from __future__ import annotations

import math

import numpy as np

from afvsgp_gym.envs import primitives as pr
from afvsgp_gym.envs.scenario import ObstacleSpec, bounding_radius

__all__ = [
    "ARM_SWEEP",
    "CLUTTER_KINDS",
    "FOREARM",
    "READY_CENTER",
    "SHELF",
    "SHELF_REFERENCE",
    "draw_tabletop",
    "shelf_obstacles",
    "tabletop_template",
]

#: The end-effector at the ready pose (m, rounded): the reference centre ``c``.
READY_CENTER = np.array([0.307, 0.0, 0.487])
#: The arm's swept volume under the tracker of the y reference, grown by 4-5 cm: a box
#: (lower, upper corner, m, world frame) above the clutter and a vertical column (radius, m)
#: about the base. Clutter whose bounding ball is outside both is off the path.
ARM_SWEEP = {"box": (np.array([-0.30, -0.42, 0.345]), np.array([0.48, 0.46, 1.0])),
             "column": 0.25}
#: Kinds of the clutter, in order (4 boxes, 3 capsules, 3 spheres), and their size ranges (m).
CLUTTER_KINDS = ("box",) * 4 + ("capsule",) * 3 + ("sphere",) * 3
_BOX_HALF = (0.03, 0.08)
_CAPSULE_RADIUS, _CAPSULE_HALF = (0.02, 0.04), (0.05, 0.12)
_SPHERE_RADIUS = (0.03, 0.07)
#: Region (lower, upper corner, m) the clutter centres are drawn from: about the path, in
#: front of it and under it (the table is at the mount, 0.49 m under the path, so the clutter
#: stands in the air like the content of racks around the robot).
_CLUTTER_REGION = (np.array([0.2, -0.5, 0.15]), np.array([0.7, 0.5, 0.55]))
_CLEARANCE = 0.02  # m between clutter items and from the forearm's sweep
#: Sizes drawn for a clutter item before its placement gives up (each with 1000 places).
PLACEMENT_ROUNDS = 50
#: The moving forearm: a capsule along x (radius, half length, m) that comes in from
#: ``travel`` m in front of the path (+x) to rest across the path's far end at
#: ``c + (0, +-along, dz)``, like the dynamic scenario's sphere, and yields: it stops (within
#: ``speed * STOP_DURATION / 2``) once a safety sphere is ``yield_distance`` m from it, as a
#: person would. Without it the scene is not solvable: an unyielding forearm can pin an arm
#: that a policy has put against a joint limit and a box (no action, of any torque, meets
#: every barrier's constraint).
FOREARM = {"radius": 0.04, "half_length": 0.15, "travel": 0.5, "along": (0.17, 0.24),
           "dz": (-0.09, -0.06), "speed": (0.15, 0.25), "delay": (0.0, 1.0),
           "yield_distance": 0.05}
#: The shelf scene's reference: the cyclic motion along x about ``c + offset``, amplitude
#: (m), into the shelf's opening and back.
SHELF_REFERENCE = {"offset": np.array([0.1, 0.0, 0.0]), "amplitude": 0.2}


def _yaw_quat(angle: float) -> np.ndarray:
    return np.array([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])


def _rotation_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _table() -> ObstacleSpec:
    """The table the robot stands on: a plane at the mount (z = 0), normal up."""
    return ObstacleSpec.of_shape(pr.Plane(np.zeros(3), np.array([0.0, 0.0, 1.0])))


def _forearm(c: np.ndarray, side: float, along: float, dz: float, start_time: float,
             speed: float) -> ObstacleSpec:
    f = FOREARM
    centre = c + np.array([0.0, side * along, dz])
    shape = pr.Capsule(centre, np.array([1.0, 0.0, 0.0]), f["half_length"], f["radius"])
    return ObstacleSpec.of_shape(shape, centre + np.array([f["travel"], 0.0, 0.0]),
                                 start_time, speed, f["yield_distance"])


def tabletop_template(c: np.ndarray, warmup_time: float) -> list[ObstacleSpec]:
    """The tabletop's obstacles at their largest sizes (the MuJoCo geoms are built from them,
    so a drawn scene only shrinks them): table, forearm, then :data:`CLUTTER_KINDS` far away."""
    out = [_table(), _forearm(c, 1.0, FOREARM["along"][1], FOREARM["dz"][1],
                              warmup_time, FOREARM["speed"][1])]
    for i, kind in enumerate(CLUTTER_KINDS):
        far = np.array([2.0 + 0.3 * i, 2.0, 0.5])
        if kind == "box":
            shape = pr.Box(far, np.eye(3), np.full(3, _BOX_HALF[1]))
        elif kind == "capsule":
            shape = pr.Capsule(far, np.array([1.0, 0.0, 0.0]), _CAPSULE_HALF[1],
                               _CAPSULE_RADIUS[1])
        else:
            shape = pr.Sphere(far, _SPHERE_RADIUS[1])
        out.append(ObstacleSpec.of_shape(shape))
    return out


def _ball_box_distance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    return float(np.linalg.norm(np.maximum(np.maximum(lo - p, 0.0), p - hi)))


def _ball_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = float(np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


def off_path(p: np.ndarray, radius: float) -> bool:
    """Whether a ball (centre ``p``, ``radius``) is outside :data:`ARM_SWEEP`."""
    lo, hi = ARM_SWEEP["box"]
    return (_ball_box_distance(p, lo, hi) >= radius
            and math.hypot(p[0], p[1]) >= ARM_SWEEP["column"] + radius)


def draw_tabletop(rng: np.random.Generator, c: np.ndarray,
                  warmup_time: float) -> list[ObstacleSpec]:
    """One tabletop scene drawn with ``rng``: the table, the forearm (side, place, speed and
    start 0-1 s after the warm-up drawn) and the clutter (sizes, yaw, places drawn; each
    item's bounding ball outside :data:`ARM_SWEEP`, off the forearm's sweep, on or above
    the table and apart from the others by :data:`_CLEARANCE`)."""
    f = FOREARM
    side = 1.0 if rng.random() < 0.5 else -1.0
    forearm = _forearm(c, side, rng.uniform(*f["along"]), rng.uniform(*f["dz"]),
                       warmup_time + rng.uniform(*f["delay"]), rng.uniform(*f["speed"]))
    ex = np.array([1.0, 0.0, 0.0])
    sweep = (forearm.position - f["half_length"] * ex,
             forearm.start + f["half_length"] * ex, f["radius"])
    out, placed = [_table(), forearm], []
    lo, hi = _CLUTTER_REGION
    for kind in CLUTTER_KINDS:
        yaw = rng.uniform(-math.pi, math.pi)
        # 1000 places for a drawn size; where none is free (about 1 scene in 1,400: a long
        # capsule after large boxes) another size, so that a draw never fails. A scene placed
        # at its first size, every one before this fallback existed, is drawn as before.
        for _ in range(PLACEMENT_ROUNDS):
            size = _clutter_size(rng, kind)
            for _ in range(1000):
                p = rng.uniform(lo, hi)
                shape = _clutter_shape(kind, p, size, yaw)
                r = bounding_radius(shape)
                if (p[2] - r >= 0.0 and off_path(p, r)
                        and _ball_segment_distance(p, *sweep[:2]) >= r + sweep[2] + _CLEARANCE
                        and all(np.linalg.norm(p - q) >= r + s + _CLEARANCE
                                for q, s in placed)):
                    break
            else:
                continue
            break
        else:  # pragma: no cover - a smaller size fits within a few rounds
            raise RuntimeError(f"could not place a {kind} of the tabletop clutter")
        placed.append((p, r))
        out.append(ObstacleSpec.of_shape(shape))
    return out


def _clutter_size(rng: np.random.Generator, kind: str) -> np.ndarray:
    """A clutter item's size: a box's half sizes, a capsule's (radius, half length), a
    sphere's radius."""
    if kind == "box":
        return rng.uniform(*_BOX_HALF, 3)
    if kind == "capsule":
        return np.array([rng.uniform(*_CAPSULE_RADIUS), rng.uniform(*_CAPSULE_HALF)])
    return np.array([rng.uniform(*_SPHERE_RADIUS)])


def _clutter_shape(kind: str, p: np.ndarray, size: np.ndarray, yaw: float) -> pr.Primitive:
    if kind == "box":
        return pr.Box(p, _rotation_z(yaw), size)
    if kind == "capsule":  # lying: its axis horizontal
        return pr.Capsule(p, np.array([math.cos(yaw), math.sin(yaw), 0.0]), size[1], size[0])
    return pr.Sphere(p, float(size[0]))


#: The shelf (m): inner faces of the side walls at ``y = +-half_width``, the lower board's top
#: ``below`` under ``c``, the upper board's underside ``above`` over ``c``, the back wall's
#: inner face ``back`` in front of ``c`` (inside the reach of the x reference, so the
#: tracker alone runs into it), the opening ``front`` in front of ``c``, boards and walls
#: ``thickness`` thick.
SHELF = {"half_width": 0.2, "below": 0.14, "above": 0.33, "back": 0.33, "front": 0.2,
         "thickness": 0.03}


def shelf_obstacles(c: np.ndarray) -> list[ObstacleSpec]:
    """The shelf's five boxes (lower board, upper board, two side walls, back wall) about the
    reference centre ``c``, and the table (a plane at the mount)."""
    s = SHELF
    t, w = s["thickness"], s["half_width"]
    x0, x1 = c[0] + s["front"], c[0] + s["back"]  # opening, back wall's inner face
    z0, z1 = c[2] - s["below"], c[2] + s["above"]  # lower board's top, upper board's bottom
    xm, depth = 0.5 * (x0 + x1 + t), 0.5 * (x1 + t - x0)
    boxes = [
        ((xm, c[1], z0 - t / 2), (depth, w + t, t / 2)),  # lower board
        ((xm, c[1], z1 + t / 2), (depth, w + t, t / 2)),  # upper board
        ((xm, c[1] - w - t / 2, 0.5 * (z0 + z1)), (depth, t / 2, 0.5 * (z1 - z0))),  # walls
        ((xm, c[1] + w + t / 2, 0.5 * (z0 + z1)), (depth, t / 2, 0.5 * (z1 - z0))),
        ((x1 + t / 2, c[1], 0.5 * (z0 + z1)), (t / 2, w, 0.5 * (z1 - z0))),  # back wall
    ]
    out = [_table()]
    for centre, half in boxes:
        out.append(ObstacleSpec.of_shape(pr.Box(np.array(centre), np.eye(3), np.array(half))))
    return out
