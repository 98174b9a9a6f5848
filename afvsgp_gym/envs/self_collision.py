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
(:func:`chain_index`): links 1-7, and the hand with both (rigid) fingers as one link after
link7 (a sphere on link7 beyond the flange plane belongs to the hand). The base (link0) has
no sphere and is left out. Spheres of one link never move apart, and those of neighbouring
links overlap round their joint by construction: only pairs on links at least two apart are
candidates (:func:`non_adjacent_pairs`: 146 of the 210 pairs of
:data:`~afvsgp_gym.envs.safety_spheres.PANDA_ARM_SPHERES`). Of these,
:data:`PANDA_SELF_COLLISION_PAIRS` keeps 67 (:func:`select_pairs`):

- 1 pair overlaps at the ready pose ``Q_HOME`` (``link5[9]/link7[15]``, the wrist's
  spheres round joint 6): it would be violated at every reset and is left out;
- 78 pairs cannot come within :data:`SELF_COLLISION_CLEARANCE` (0.01 m) of each other
  anywhere within the MuJoCo model's joint ranges, and are left out: the least ``h`` of
  :data:`SELECTION_SAMPLES` configurations drawn uniformly within the ranges (seed
  :data:`SELECTION_SEED`), refined by L-BFGS-B from the pair's :data:`REFINE_STARTS` best
  samples, is at least that.

``benchmarks/select_self_pairs.py`` regenerates the table and writes every candidate's
minima and minimiser to ``benchmarks/results/self_pairs.json``; tests/envs/test_self_collision.py
checks the table against that file and re-checks the file in part.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from afvsgp_gym.envs.safety_spheres import SafetySphere
from afvsgp_gym.envs.scenario import sphere_barriers

__all__ = ["FLANGE_HEIGHT", "HAND_INDEX", "PANDA_SELF_COLLISION_PAIRS", "REFINE_STARTS",
           "SELECTION_SAMPLES", "SELECTION_SEED", "SELF_COLLISION_CLEARANCE",
           "SelfCollisionPairs", "SelfPairGeometry", "chain_index", "non_adjacent_pairs",
           "select_pairs"]

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
#: The chain index of the hand and the fingers: one link after link7.
HAND_INDEX = 8

# The kept pairs: sphere index of PANDA_ARM_SPHERES -> the spheres it is paired with
# (benchmarks/select_self_pairs.py prints this table).
_KEPT: dict[int, tuple[int, ...]] = {
    0: (8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20),
    1: (9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20),
    2: (8, 10, 14, 15, 16, 17, 18, 19, 20),
    3: (9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20),
    5: (20,),
    7: (19, 20),
    8: (15, 16, 17, 18, 19, 20),
    9: (14, 16, 17),
    10: (14, 15, 16, 17, 18, 19),
    11: (14, 15, 16),
}

#: ``(a, b)`` sphere indices into ``PANDA_ARM_SPHERES``, ``a < b`` (module docstring).
PANDA_SELF_COLLISION_PAIRS: tuple[tuple[int, int], ...] = tuple(
    (a, b) for a, partners in _KEPT.items() for b in partners)


def chain_index(body: str, offset_z: float = 0.0) -> int:
    """Place in the kinematic chain of a point on ``body`` at height ``offset_z`` (m, body
    frame): k for ``panda0_link<k>`` (1-7), :data:`HAND_INDEX` for the fingers and for link7
    beyond the flange (the hand). ``ValueError`` for any other body (link0 included)."""
    name = body.removeprefix("panda0_")
    if name in ("leftfinger", "rightfinger"):
        return HAND_INDEX
    k = name.removeprefix("link")
    if k.isdigit() and 1 <= int(k) <= 7:
        return HAND_INDEX if int(k) == 7 and offset_z > FLANGE_HEIGHT else int(k)
    raise ValueError(f"body {body!r} is not a moving link of the Panda "
                     f"(panda0_link1..panda0_link7, panda0_leftfinger, panda0_rightfinger)")


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
    """Sphere pairs ``(first[i], second[i])`` with radius sums ``radius`` (P,); build with
    :meth:`of`. Arrays indexed by sphere have the sphere set's order.

    Example (any kinematics; here every centre on the z axis, 0.3 m apart, at rest):
        >>> import numpy as np
        >>> from afvsgp_gym.envs.safety_spheres import PANDA_ARM_SPHERES
        >>> pairs = SelfCollisionPairs.of(PANDA_ARM_SPHERES)
        >>> p = np.outer(0.3 * np.arange(21), [0.0, 0.0, 1.0])
        >>> geometry = pairs.geometry(p, np.zeros((21, 3)))
        >>> len(pairs), pairs.names(PANDA_ARM_SPHERES)[0], round(float(geometry.h[0]), 4)
        (67, 'link1[0]/link5[8]', 2.2336)
    """

    first: np.ndarray
    second: np.ndarray
    radius: np.ndarray

    @classmethod
    def of(cls, spheres: Sequence[SafetySphere],
           pairs: Sequence[tuple[int, int]] = PANDA_SELF_COLLISION_PAIRS
           ) -> SelfCollisionPairs:
        """The ``pairs`` (sphere indices) of ``spheres``; ``ValueError`` for an index out of
        range or a sphere paired with itself."""
        idx = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        if idx.size and (idx.min() < 0 or idx.max() >= len(spheres)):
            raise ValueError(f"pairs must index the {len(spheres)} spheres. Got: {pairs!r}")
        if np.any(idx[:, 0] == idx[:, 1]):
            raise ValueError(f"pairs must join two different spheres. Got: {pairs!r}")
        radii = np.array([s.radius for s in spheres], dtype=np.float64)
        return cls(idx[:, 0].copy(), idx[:, 1].copy(), radii[idx[:, 0]] + radii[idx[:, 1]])

    def __len__(self) -> int:
        return len(self.radius)

    def names(self, spheres: Sequence[SafetySphere]) -> tuple[str, ...]:
        """``"link1[0]/link7[14]"``: each pair's bodies and sphere indices."""
        def name(i: int) -> str:
            return f"{spheres[i].body.removeprefix('panda0_')}[{i}]"
        return tuple(f"{name(a)}/{name(b)}" for a, b in zip(self.first, self.second,
                                                           strict=True))

    def geometry(self, p: np.ndarray, v: np.ndarray) -> SelfPairGeometry:
        """The pairs' geometry from the sphere centres ``p`` and velocities ``v`` (S, 3)."""
        offset = p[self.first] - p[self.second]
        v_rel = v[self.first] - v[self.second]
        h, hd, n, curv = sphere_barriers(offset, v_rel, self.radius)
        return SelfPairGeometry(h, hd, n, curv, offset, v_rel)

    def rows(self, geometry: SelfPairGeometry, jac: np.ndarray) -> np.ndarray:
        """``n'(J_a - J_b)`` (P, nv) from the centres' Jacobians ``jac`` (S, 3, nv): ``h' =
        rows q'``, and a joint-acceleration error ``Delta q''`` moves ``h''`` by ``rows
        Delta q''``."""
        return np.einsum("pi,pij->pj", geometry.n, jac[self.first] - jac[self.second])

    def terms(self, geometry: SelfPairGeometry, acceleration: np.ndarray,
              gain: np.ndarray | None, n_actions: int) -> tuple[np.ndarray, np.ndarray]:
        """``lf`` (P,) and ``lg`` (P, n_actions) from the centres' accelerations at zero
        action ``acceleration`` (S, 3) and their gain per action unit ``gain`` (S, 3,
        n_actions; ``J_s M^-1 diag(action_scale)``), or ``lg = 0`` when ``gain`` is None (a
        model that knows the kinematics only)."""
        n = geometry.n
        lf = np.einsum("pi,pi->p", n, acceleration[self.first] - acceleration[self.second])
        lf += geometry.curvature
        if gain is None:
            return lf, np.zeros((len(self), n_actions))
        return lf, np.einsum("pi,pij->pj", n, gain[self.first] - gain[self.second])

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
