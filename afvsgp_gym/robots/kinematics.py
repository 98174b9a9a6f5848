"""Forward kinematics of the Franka arm's safety spheres from DH parameters (numpy only).

Franka documents the Panda's (and the FR3's, which shares the table) kinematics in Craig's
modified Denavit-Hartenberg convention (Franka Control Interface documentation, "Robot and
interface specifications", "Denavit-Hartenberg parameters"): frame ``i`` follows frame
``i - 1`` by

``T_{i-1,i} = Rot_x(alpha_i) Trans_x(a_i) Rot_z(theta_i) Trans_z(d_i)``,
``theta_i = q_i + theta_offset_i``,

=====  ========  =======  ==========
joint  a (m)     d (m)    alpha (rad)
=====  ========  =======  ==========
1      0         0.333    0
2      0         0        -pi/2
3      0         0.316    pi/2
4      0.0825    0        pi/2
5      -0.0825   0.384    -pi/2
6      0         0        pi/2
7      0.088     0        pi/2
=====  ========  =======  ==========

(the flange is 0.107 m along z7). Frame ``i`` rotates with joint ``i`` about its own z axis.

**The gymnasium-robotics Panda** (:mod:`afvsgp_gym.envs.franka_model`, the simulation's and
the stand-in's) has the same bodies with two differences, found by comparing its body frames
with the table above at random joint angles (tests/robots/test_kinematics.py):

- its link frames 1-5 are Franka's DH frames 1-5 exactly;
- its link 6 and link 7 bodies are Franka's DH frames 6 and 7 with the joint zero shifted,
  ``theta_6 = q_6 + 1.57`` and ``theta_7 = q_7 + 0.7854`` (MJCF ``euler='1.57 0 1.57'`` and
  ``euler='1.57 0 0.7854'``), and the MJCF writes ``alpha_6 = alpha_7 = 1.57`` where Franka's
  table has pi/2 (8e-4 rad less; the spheres then sit up to ~0.5 mm from where Franka's table
  puts them, :data:`GYMNASIUM_PANDA` vs :data:`FRANKA_PANDA`).

:data:`GYMNASIUM_PANDA` is that variant of the table; with it the spheres, their Jacobians and
``J' q'`` equal MuJoCo's (``mj_kinematics``, ``mj_jac``, ``mj_jacDot``) to 1e-9. The safety
spheres of :data:`~afvsgp_gym.envs.safety_spheres.PANDA_ARM_SPHERES` are given in the
gymnasium-robotics body frames, which are the DH frames of the same link, so the same offsets
serve both chains: on a real robot use :data:`FRANKA_PANDA` with the angles the robot
reports. (A gymnasium-robotics angle ``q`` is Franka's ``q + (0, 0, 0, 0, 0, 1.57, 0.7854)``:
the MJCF's joint-6 range is Franka's shifted by 1.57 rad, to 0.07 rad, and its hand is
mounted -45 degrees about z from link 7 as Franka's is from the flange; its joint-7 range was
not shifted. :func:`~afvsgp_gym.robots.libfranka.check_kinematics` compares the table with a
connected robot's own flange pose and Jacobian before the bridge starts.)

Velocities (frame ``i`` has axis ``z_i`` and origin ``o_i`` in the base frame, ``S`` a sphere
centre ``p`` on link ``k``):

- ``J = [z_i x (p - o_i)]_{i <= k}`` (3, 7), ``v = J q'``;
- ``w_i = sum_{j <= i} q'_j z_j`` (frame ``i``'s angular velocity), ``z_i' = w_i x z_i``,
  ``o_i' = o_{i-1}' + w_{i-1} x (o_i - o_{i-1})``;
- ``J' q' = sum_{i <= k} q'_i [z_i' x (p - o_i) + z_i x (v - o_i')]``, the velocity-product
  term of ``p'' = J q'' + J' q'`` that ``h''`` needs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from afvsgp_gym import _compiled

_arm = _compiled.extension("arm")

__all__ = ["END_EFFECTOR_OFFSET", "FLANGE_OFFSET", "FRANKA_PANDA", "GYMNASIUM_PANDA", "DHChain",
           "SphereKinematics"]

#: The end-effector point in link 7's frame (m): the simulation's ``end_effector`` site,
#: on the real arm the flange (0.107 m) plus the Franka Hand's 0.1034 m.
END_EFFECTOR_OFFSET = (0.0, 0.0, 0.21)
#: The flange frame F: frame 7 moved this far (m) along its z axis (Franka's table).
FLANGE_OFFSET = 0.107


def _array7(value, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (7,) or not np.isfinite(arr).all():
        raise ValueError(f"{name} must be 7 finite numbers. Got: {value!r}")
    arr = arr.copy()
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True)
class DHChain:
    """A 7-joint revolute arm in modified (Craig) DH parameters.

    Parameters
    ----------
    a, d, alpha : array_like of shape (7,)
        ``a_i`` (m), ``d_i`` (m), ``alpha_i`` (rad) of ``T_{i-1,i}`` (module docstring).
    theta_offset : array_like of shape (7,)
        ``theta_i = q_i + theta_offset_i`` (rad).
    name : str
        For messages and the docs.
    """

    a: np.ndarray
    d: np.ndarray
    alpha: np.ndarray
    theta_offset: np.ndarray = field(default_factory=lambda: np.zeros(7))
    name: str = "arm"

    def __post_init__(self) -> None:
        for key in ("a", "d", "alpha", "theta_offset"):
            object.__setattr__(self, key, _array7(getattr(self, key), key))
        # the fixed part of every T_{i-1,i}: Rot_x(alpha_i) Trans_x(a_i), (7, 3, 3) and (7, 3)
        ca, sa = np.cos(self.alpha), np.sin(self.alpha)
        rx = np.zeros((7, 3, 3))
        rx[:, 0, 0] = 1.0
        rx[:, 1, 1], rx[:, 1, 2] = ca, -sa
        rx[:, 2, 1], rx[:, 2, 2] = sa, ca
        object.__setattr__(self, "_rx", rx)
        shift = rx[:, :, 0] * self.a[:, None] + rx[:, :, 2] * self.d[:, None]
        object.__setattr__(self, "_shift", shift)

    def frames(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations ``R_i`` (7, 3, 3) and origins ``o_i`` (7, 3) of frames 1-7 in the base
        frame at joint angles ``q`` (7,)."""
        theta = np.asarray(q, dtype=np.float64) + self.theta_offset
        rz = np.zeros((7, 3, 3))
        ct, st = np.cos(theta), np.sin(theta)
        rz[:, 0, 0] = rz[:, 1, 1] = ct
        rz[:, 1, 0], rz[:, 0, 1] = st, -st
        rz[:, 2, 2] = 1.0
        local = np.matmul(self._rx, rz)  # Rot_x(alpha_i) Rot_z(theta_i)
        # the origin of frame i in frame i-1: Rot_x(alpha_i) ([a_i, 0, 0] + [0, 0, d_i])
        shift = self._shift
        rot = np.empty((7, 3, 3))
        rot[0] = local[0]
        for i in range(1, 7):
            np.matmul(rot[i - 1], local[i], out=rot[i])
        org = np.empty((7, 3))
        org[0] = shift[0]
        org[1:] = np.einsum("kij,kj->ki", rot[:-1], shift[1:])
        np.cumsum(org, axis=0, out=org)
        return rot, org

    def flange(self, q: np.ndarray) -> np.ndarray:
        """The flange frame's pose ``O_T_F`` (4, 4) at ``q``: frame 7 moved
        :data:`FLANGE_OFFSET` along its z axis."""
        rot, org = self.frames(q)
        out = np.eye(4)
        out[:3, :3] = rot[6]
        out[:3, 3] = org[6] + FLANGE_OFFSET * rot[6][:, 2]
        return out


#: Franka's documented table (Panda and FR3): the robot's own angles.
FRANKA_PANDA = DHChain(
    a=(0.0, 0.0, 0.0, 0.0825, -0.0825, 0.0, 0.088),
    d=(0.333, 0.0, 0.316, 0.0, 0.384, 0.0, 0.0),
    alpha=(0.0, -math.pi / 2, math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2, math.pi / 2),
    name="franka",
)

#: The gymnasium-robotics Panda of the simulation (module docstring): Franka's table with
#: ``alpha_6 = alpha_7 = 1.57`` and the joint zeros of joints 6 and 7 shifted.
GYMNASIUM_PANDA = DHChain(
    a=FRANKA_PANDA.a,
    d=FRANKA_PANDA.d,
    alpha=(0.0, -math.pi / 2, math.pi / 2, math.pi / 2, -math.pi / 2, 1.57, 1.57),
    theta_offset=(0.0, 0.0, 0.0, 0.0, 0.0, 1.57, 0.7854),
    name="gymnasium-robotics",
)


class SphereKinematics:
    """Centres, velocities, Jacobians and ``J' q'`` of points fixed to the links of a chain.

    Parameters
    ----------
    chain : DHChain
    links : sequence of int, shape (S,)
        The link (1-7) each point is fixed to.
    offsets : array_like of shape (S, 3)
        Each point in its link's frame (m).
    backend : {"auto", "numpy", "compiled"}
        :meth:`__call__`'s arithmetic (:mod:`afvsgp_gym._compiled`, the extension ``"arm"``;
        the numpy path is the reference, the two agree to rounding).
    """

    def __init__(self, chain: DHChain, links: Sequence[int], offsets, *,
                 backend: str | _compiled.Backend = "auto") -> None:
        if not isinstance(chain, DHChain):
            raise ValueError(f"chain must be a DHChain. Got: {chain!r}")
        link = np.asarray(links)
        off = np.asarray(offsets, dtype=np.float64)
        if link.ndim != 1 or not len(link) or not np.issubdtype(link.dtype, np.integer) \
                or np.any((link < 1) | (link > 7)):
            raise ValueError(f"links must be a non-empty sequence of integers 1-7. Got: {links!r}")
        if off.shape != (len(link), 3) or not np.isfinite(off).all():
            raise ValueError(f"offsets must be finite with shape ({len(link)}, 3). "
                             f"Got shape {off.shape}")
        self.chain = chain
        self.links = link.astype(np.int64)
        self.offsets = off.copy()
        self._frame = self.links - 1
        # [i, s, 0]: 1 where joint i moves point s
        self._mask_cols = (np.arange(7)[:, None] <= self._frame[None, :]).astype(
            np.float64)[:, :, None]
        self._offset_cols = np.ascontiguousarray(self.offsets[:, :, None])
        self.backend = _compiled.resolve(backend, ("arm",))
        self._chain_c = (chain.theta_offset, chain._rx, chain._shift)  # the extension's

    @classmethod
    def from_spheres(cls, chain: DHChain, spheres: Sequence, *,
                     backend: str | _compiled.Backend = "auto") -> SphereKinematics:
        """From :class:`~afvsgp_gym.envs.safety_spheres.SafetySphere` entries on bodies named
        ``...link<i>`` (i = 1-7)."""
        links = []
        for k, s in enumerate(spheres):
            name = str(s.body)
            tail = name.rsplit("link", 1)[-1] if "link" in name else ""
            if not tail.isdigit() or not 1 <= int(tail) <= 7:
                raise ValueError(f"spheres[{k}].body must name link1..link7. Got: {name!r}")
            links.append(int(tail))
        return cls(chain, links, [s.offset for s in spheres], backend=backend)

    def positions(self, q: np.ndarray) -> np.ndarray:
        """``(S, 3)`` point positions at ``q``."""
        if self.backend.arm:  # the same digits as __call__'s
            return self(q, np.zeros(7))[0]
        rot, org = self.chain.frames(q)
        f = self._frame
        return np.matmul(rot[f], self._offset_cols)[:, :, 0] + org[f]

    def __call__(self, q: np.ndarray, qd: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(p (S, 3), v (S, 3), J (S, 3, 7), J' q' (S, 3))`` at joint angles ``q`` and
        velocities ``qd`` (module docstring for the formulas; ``v`` and ``J' q'`` through the
        frames' velocities and velocity-product accelerations, summed over the chain once)."""
        q = np.asarray(q, dtype=np.float64)
        qd = np.asarray(qd, dtype=np.float64)
        if self.backend.arm:
            n = len(self._frame)
            p, v, acc = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
            jac = np.empty((n, 3, 7))
            _arm.kinematics(n, np.ascontiguousarray(q), np.ascontiguousarray(qd),
                            *self._chain_c, self._frame, self.offsets, p, v, jac, acc)
            return p, v, jac, acc
        rot, org = self.chain.frames(q)
        f = self._frame
        p = np.matmul(rot[f], self._offset_cols)[:, :, 0] + org[f]
        z = rot[:, :, 2]  # (7, 3) joint axes
        # J: row-wise z_i x (p - o_i) = (p - o_i) [z_i]_x^T, one batched product
        cols = np.matmul(p[None, :, :] - org[:, None, :], _skew(z).transpose(0, 2, 1))
        cols *= self._mask_cols  # (7, S, 3), 0 where joint i does not move point s
        jac = cols.transpose(1, 2, 0)  # (S, 3, 7)
        # frames: w_i = sum_{j<=i} q'_j z_j, the bias angular acceleration
        # b_i = sum_{j<=i} q'_j (w_j x z_j) and K_i = [b_i]_x + [w_i]_x^2, so that a point r
        # from the origin of frame i has v = v_o + w x r and J' q' = a_o + K r; the origins
        # (o_1 fixed; o_{i+1} rides on frame i at e_i = o_{i+1} - o_i) add [w_i]_x e_i and
        # K_i e_i
        w = np.cumsum(qd[:, None] * z, axis=0)
        ws = _skew(w)
        b = np.cumsum(qd[:, None] * np.matmul(ws, z[:, :, None])[:, :, 0], axis=0)
        k = _skew(b)
        k += np.matmul(ws, ws)
        e = (org[1:] - org[:-1])[:, :, None]
        grow = np.matmul(np.concatenate((ws[:-1], k[:-1])), np.concatenate((e, e)))[:, :, 0]
        vo = np.zeros((7, 3))
        ao = np.zeros((7, 3))
        np.cumsum(grow[:6], axis=0, out=vo[1:])
        np.cumsum(grow[6:], axis=0, out=ao[1:])
        r = (p - org[f])[:, :, None]
        v = vo[f] + np.matmul(ws[f], r)[:, :, 0]
        acc = ao[f] + np.matmul(k[f], r)[:, :, 0]
        return p, v, jac, acc


#: Where ``[a]_x`` (flattened 3 x 3) takes which component of ``a``, with which sign.
_SKEW_AT = np.array([1, 2, 3, 5, 6, 7])
_SKEW_OF = np.array([2, 1, 2, 0, 1, 0])
_SKEW_SIGN = np.array([-1.0, 1.0, 1.0, -1.0, -1.0, 1.0])


def _skew(a: np.ndarray) -> np.ndarray:
    """``[a]_x`` (n, 3, 3) of the rows of ``a`` (n, 3): ``[a]_x b = a x b``."""
    out = np.zeros((a.shape[0], 9))
    out[:, _SKEW_AT] = a[:, _SKEW_OF] * _SKEW_SIGN
    return out.reshape(-1, 3, 3)
