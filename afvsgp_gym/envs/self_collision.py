"""Self-collision barriers: pairs of safety spheres on links of the arm that can meet.

Numpy only (no simulator): given the spheres' centres, velocities, Jacobians and
accelerations at zero action, from any kinematics, :class:`SelfCollisionPairs` gives the
barrier terms of every pair ``(a, b)``, relative degree 2, as the obstacle pairs'
(:func:`~afvsgp_gym.envs.scenario.sphere_barriers`):

- ``h = |p_a - p_b| - r_a - r_b``, ``n = (p_a - p_b) / |p_a - p_b|``, ``h' = n'(v_a - v_b)``;
- ``h'' = lf + lg u`` with ``lf = n'(acc_a - acc_b) + (|v_rel|^2 - (n' v_rel)^2) / |p_a - p_b|``
  (the curvature term, >= 0; ``acc_s = J_s q''_0 + J_s' q'``) and
  ``lg = n'(J_a M^-1 - J_b M^-1) diag(action_scale)``.

**Which pairs.** A sphere's link is its place in the kinematic chain
(:func:`chain_index`): the base (link0) 0, links 1-7, and the hand with both (rigid)
fingers as one link after link7 (a sphere on link7 beyond the flange plane belongs to the
hand). The spheres are :data:`PANDA_SELF_COLLISION_SPHERES`: the arm's 21 and the base's 2
(:data:`~afvsgp_gym.envs.safety_spheres.PANDA_BASE_SPHERES`, for these barriers only; the
base does not move, so its spheres have zero velocity and Jacobian and a pair with one has
the moving sphere's terms). Spheres of one link never move apart, and those of neighbouring
links overlap round their joint by construction: only pairs on links at least two apart are
candidates (:func:`non_adjacent_pairs`: 184 of the 253 pairs, 38 of them with the base;
link0-link1 are neighbours, link0-link2 are two apart and candidates by this rule).
Of these, :data:`PANDA_SELF_COLLISION_PAIRS` keeps 93 (:func:`select_pairs`), 26 of them
with the base (its spheres with those of links 5-7 and the hand):

- 1 pair overlaps at the ready pose ``Q_HOME`` (``link5[9]/link7[15]``, the wrist's
  spheres round joint 6): it would be violated at every reset and is left out;
- 90 pairs cannot come within :data:`SELF_COLLISION_CLEARANCE` (0.01 m) of each other
  anywhere within the MuJoCo model's joint ranges, and are left out: the least ``h`` of
  :data:`SELECTION_SAMPLES` configurations drawn uniformly within the ranges (seed
  :data:`SELECTION_SEED`), refined by L-BFGS-B from the pair's :data:`REFINE_STARTS` best
  samples, is at least that. Among them are all 12 pairs of the base with links 2-4
  (link2's at least 0.089 m away).

``benchmarks/select_self_pairs.py`` regenerates the table and writes every candidate's
minima and minimiser to ``benchmarks/results/self_pairs.json``; tests/envs/test_self_collision.py
checks the table against that file and re-checks the file in part.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from afvsgp_gym.envs.safety_spheres import PANDA_ARM_SPHERES, PANDA_BASE_SPHERES, SafetySphere
from afvsgp_gym.envs.scenario import sphere_barriers

__all__ = ["BASE_INDEX", "FLANGE_HEIGHT", "HAND_INDEX", "PANDA_SELF_COLLISION_PAIRS",
           "PANDA_SELF_COLLISION_SPHERES", "REFINE_STARTS", "SELECTION_SAMPLES",
           "SELECTION_SEED", "SELF_COLLISION_CLEARANCE", "SelfCollisionPairs",
           "SelfPairGeometry", "chain_index", "non_adjacent_pairs", "select_pairs"]

#: m: a pair is a barrier only when its least ``h`` over the joint ranges (refined) is below
#: this: the pairs that can touch, and a centimetre more for a minimiser that stops short.
SELF_COLLISION_CLEARANCE = 0.01
#: Joint configurations sampled to choose the pairs, and their seed.
SELECTION_SAMPLES = 20000
SELECTION_SEED = 0
#: Local minimisations of each pair's ``h``, from its best samples.
REFINE_STARTS = 5
#: m along link7's z axis: the flange plane (``franka_model.FLANGE_POS``); a sphere on link7
#: beyond it lies on the hand.
FLANGE_HEIGHT = 0.107
#: The chain index of the base (link0) and of the hand with the fingers (one link after
#: link7).
BASE_INDEX = 0
HAND_INDEX = 8
#: The spheres the pairs index: the arm's (``PANDA_ARM_SPHERES``, 0-20) and the base's
#: (``PANDA_BASE_SPHERES``, 21-22), which do not move.
PANDA_SELF_COLLISION_SPHERES: tuple[SafetySphere, ...] = PANDA_ARM_SPHERES + PANDA_BASE_SPHERES

# The kept pairs: sphere index of PANDA_SELF_COLLISION_SPHERES -> the spheres it is paired
# with (benchmarks/select_self_pairs.py prints this table).
_KEPT: dict[int, tuple[int, ...]] = {
    0: (8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20),
    1: (9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20),
    2: (8, 10, 14, 15, 16, 17, 18, 19, 20),
    3: (9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20),
    5: (20,),
    7: (19, 20),
    8: (15, 16, 17, 18, 19, 20, 21, 22),
    9: (14, 16, 17, 21, 22),
    10: (14, 15, 16, 17, 18, 19, 21, 22),
    11: (14, 15, 16, 21, 22),
    12: (21, 22),
    13: (21, 22),
    14: (21, 22),
    15: (21, 22),
    16: (21, 22),
    17: (21, 22),
    18: (21, 22),
    19: (21, 22),
    20: (21, 22),
}

#: ``(a, b)`` sphere indices into ``PANDA_SELF_COLLISION_SPHERES``, ``a < b`` (module
#: docstring).
PANDA_SELF_COLLISION_PAIRS: tuple[tuple[int, int], ...] = tuple(
    (a, b) for a, partners in _KEPT.items() for b in partners)


def chain_index(body: str, offset_z: float = 0.0) -> int:
    """Place in the kinematic chain of a point on ``body`` at height ``offset_z`` (m, body
    frame): k for ``panda0_link<k>`` (0-7; :data:`BASE_INDEX` for the base), :data:`HAND_INDEX`
    for the fingers and for link7 beyond the flange (the hand). ``ValueError`` for any other
    body."""
    name = body.removeprefix("panda0_")
    if name in ("leftfinger", "rightfinger"):
        return HAND_INDEX
    k = name.removeprefix("link")
    if k.isdigit() and 0 <= int(k) <= 7:
        return HAND_INDEX if int(k) == 7 and offset_z > FLANGE_HEIGHT else int(k)
    raise ValueError(f"body {body!r} is not a link of the Panda "
                     f"(panda0_link0..panda0_link7, panda0_leftfinger, panda0_rightfinger)")


def non_adjacent_pairs(spheres: Sequence[SafetySphere]) -> np.ndarray:
    """``(C, 2)`` index pairs ``a < b`` of the ``spheres`` on links at least two apart in
    the chain (:func:`chain_index`)."""
    index = np.array([chain_index(s.body, s.offset[2]) for s in spheres])
    a, b = np.triu_indices(len(index), 1)
    keep = np.abs(index[a] - index[b]) >= 2
    return np.column_stack([a[keep], b[keep]])


def select_pairs(candidates: np.ndarray, home_h: np.ndarray, closest_h: np.ndarray,
                 clearance: float = SELF_COLLISION_CLEARANCE) -> np.ndarray:
    """The ``candidates`` (C, 2) not overlapping at the ready pose (``home_h`` >= 0) whose
    least ``h`` over the joint ranges (``closest_h``, (C,)) is below ``clearance``."""
    keep = (np.asarray(home_h) >= 0.0) & (np.asarray(closest_h) < clearance)
    return np.asarray(candidates)[keep]


class SelfPairGeometry(NamedTuple):
    """The kinematic part of P self-collision barriers at one state: ``h``, ``hd`` (P,),
    unit normals ``n`` (P, 3) from ``b`` to ``a``, ``curvature`` (P,), ``offset`` = ``p_a -
    p_b`` and ``v_rel`` = ``v_a - v_b`` (P, 3)."""

    h: np.ndarray
    hd: np.ndarray
    n: np.ndarray
    curvature: np.ndarray
    offset: np.ndarray
    v_rel: np.ndarray


@dataclass(frozen=True)
class SelfCollisionPairs:
    """Sphere pairs ``(first[i], second[i])`` with radius sums ``radius`` (P,) of a sphere set
    whose last ``len(fixed)`` spheres do not move (at the world centres ``fixed``, (F, 3));
    build with :meth:`of`. The methods take the arrays of the set's first ``n_moving``
    spheres, which move; a fixed sphere has zero velocity, Jacobian and acceleration,
    so a pair with one has the moving sphere's terms alone.

    Example (any kinematics; here every centre on the z axis, 0.3 m apart, at rest, and the
    base's spheres where they are on the Panda, link0's frame the world's):
        >>> import numpy as np
        >>> from afvsgp_gym.envs.safety_spheres import PANDA_BASE_SPHERES
        >>> base = np.array([s.offset for s in PANDA_BASE_SPHERES])
        >>> pairs = SelfCollisionPairs.of(PANDA_SELF_COLLISION_SPHERES, fixed_centres=base)
        >>> p = np.outer(0.3 * np.arange(21), [0.0, 0.0, 1.0])
        >>> geometry = pairs.geometry(p, np.zeros((21, 3)))
        >>> len(pairs), pairs.n_moving, pairs.names(PANDA_SELF_COLLISION_SPHERES)[-1]
        (93, 21, 'link7[20]/link0[22]')
        >>> round(float(geometry.h[0]), 4), round(float(geometry.h[-1]), 4)
        (2.2336, 5.819)
    """

    first: np.ndarray
    second: np.ndarray
    radius: np.ndarray
    fixed: np.ndarray
    n_moving: int

    @classmethod
    def of(cls, spheres: Sequence[SafetySphere],
           pairs: Sequence[tuple[int, int]] = PANDA_SELF_COLLISION_PAIRS,
           fixed_centres: np.ndarray | None = None) -> SelfCollisionPairs:
        """The ``pairs`` (sphere indices) of ``spheres``, the last ``len(fixed_centres)`` of
        which are fixed at those world centres (F, 3; None: none). ``ValueError`` for an index
        out of range, a sphere paired with itself or two fixed spheres paired."""
        idx = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        fixed = (np.zeros((0, 3)) if fixed_centres is None
                 else np.array(fixed_centres, dtype=np.float64).reshape(-1, 3))
        if len(fixed) > len(spheres) or not np.all(np.isfinite(fixed)):
            raise ValueError(f"fixed_centres must be finite centres (F, 3) of the last F of the "
                             f"{len(spheres)} spheres. Got: {fixed_centres!r}")
        if idx.size and (idx.min() < 0 or idx.max() >= len(spheres)):
            raise ValueError(f"pairs must index the {len(spheres)} spheres. Got: {pairs!r}")
        if np.any(idx[:, 0] == idx[:, 1]):
            raise ValueError(f"pairs must join two different spheres. Got: {pairs!r}")
        n_moving = len(spheres) - len(fixed)
        if np.any(idx.min(axis=1, initial=len(spheres)) >= n_moving):
            raise ValueError(f"pairs must join a moving sphere (index < {n_moving}). "
                             f"Got: {pairs!r}")
        radii = np.array([s.radius for s in spheres], dtype=np.float64)
        fixed.flags.writeable = False
        return cls(idx[:, 0].copy(), idx[:, 1].copy(), radii[idx[:, 0]] + radii[idx[:, 1]],
                   fixed, n_moving)

    def __len__(self) -> int:
        return len(self.radius)

    def names(self, spheres: Sequence[SafetySphere]) -> tuple[str, ...]:
        """``"link1[0]/link7[14]"``: each pair's bodies and sphere indices."""
        def name(i: int) -> str:
            return f"{spheres[i].body.removeprefix('panda0_')}[{i}]"
        return tuple(f"{name(a)}/{name(b)}" for a, b in zip(self.first, self.second,
                                                           strict=True))

    @functools.cached_property
    def _difference(self) -> tuple[np.ndarray, np.ndarray]:
        """``(D, F)``: ``D`` (P, M) with +1 at each pair's first sphere and -1 at its second
        where that one moves, ``F`` (P, 3) the fixed second sphere's centre (else 0), so that
        ``x_a - x_b = D x`` for any per-sphere quantity of the moving spheres (a fixed sphere
        has none) and ``p_a - p_b = D p - F``: one product, each entry ``x_a - x_b`` rounded
        once, as the direct difference."""
        rows = np.arange(len(self))
        diff = np.zeros((len(self), self.n_moving))
        diff[rows, self.first] = 1.0
        moving = self.second < self.n_moving
        diff[rows[moving], self.second[moving]] = -1.0
        centres = np.zeros((len(self), 3))
        centres[~moving] = self.fixed[self.second[~moving] - self.n_moving]
        return diff, centres

    def _pair_difference(self, x: np.ndarray) -> np.ndarray:
        """``x_a - x_b`` (P, ...) of a per-sphere array ``x`` (M, ...) of the moving spheres,
        0 for a fixed sphere."""
        diff = self._difference[0]
        return (diff @ x.reshape(len(x), -1)).reshape((len(self),) + x.shape[1:])

    def geometry(self, p: np.ndarray, v: np.ndarray) -> SelfPairGeometry:
        """The pairs' geometry from the moving sphere centres ``p`` and velocities ``v``
        (M, 3)."""
        diff, centres = self._difference
        offset = diff @ p - centres
        v_rel = diff @ v
        h, hd, n, curv = sphere_barriers(offset, v_rel, self.radius)
        return SelfPairGeometry(h, hd, n, curv, offset, v_rel)

    def rows(self, geometry: SelfPairGeometry, jac: np.ndarray) -> np.ndarray:
        """``n'(J_a - J_b)`` (P, nv) from the moving centres' Jacobians ``jac`` (M, 3, nv):
        ``h' = rows q'``, and a joint-acceleration error ``Delta q''`` moves ``h''`` by ``rows
        Delta q''``."""
        return np.einsum("pi,pij->pj", geometry.n, self._pair_difference(jac))

    def lf(self, geometry: SelfPairGeometry, acceleration: np.ndarray) -> np.ndarray:
        """``lf`` (P,) from the moving centres' accelerations at zero action ``acceleration``
        (M, 3): ``n'(a_a - a_b)`` plus the curvature term of ``h''``."""
        lf = np.einsum("pi,pi->p", geometry.n, self._difference[0] @ acceleration)
        lf += geometry.curvature
        return lf

    def lg(self, geometry: SelfPairGeometry, gain: np.ndarray) -> np.ndarray:
        """``lg`` (P, n_actions) from the moving centres' gain per action unit ``gain`` (M, 3,
        n_actions; ``J_s M^-1 diag(action_scale)``)."""
        return np.einsum("pi,pij->pj", geometry.n, self._pair_difference(gain))

    def terms(self, geometry: SelfPairGeometry, acceleration: np.ndarray,
              gain: np.ndarray | None, n_actions: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`lf` and :meth:`lg`, or ``lg = 0`` (P, n_actions) when ``gain`` is None (a
        model that knows the kinematics only)."""
        lf = self.lf(geometry, acceleration)
        if gain is None:
            return lf, np.zeros((len(self), n_actions))
        return lf, self.lg(geometry, gain)

    def features(self, geometry: SelfPairGeometry, q: np.ndarray, qd: np.ndarray,
                 feature_dim: int) -> np.ndarray:
        """``xi`` (P, feature_dim) = ``[q, q', p_a - p_b, v_a - v_b]``, the obstacle pairs'
        layout with the second sphere in the obstacle's place."""
        nq = len(q)
        xi = np.zeros((len(self), feature_dim))
        xi[:, :nq] = q
        xi[:, nq : 2 * nq] = qd
        xi[:, 2 * nq : 2 * nq + 3] = geometry.offset
        xi[:, 2 * nq + 3 : 2 * nq + 6] = geometry.v_rel
        return xi
