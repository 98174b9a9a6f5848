"""The robot's own limits as barriers and as a safety check (numpy only, no simulator).

Per joint ``j`` with range ``[lo_j, hi_j]`` (rad) and speed limit ``V_j`` (rad/s), four
barriers, each with a margin inside the limit (``range_margin`` rad, ``speed_margin`` rad/s):

==============  ==============================  ===========  ==============  =====
barrier         h                               h'           degree          sign
==============  ==============================  ===========  ==============  =====
range, lower    ``q_j - lo_j - dq``             ``q'_j``     2 (``h'' = q''_j``)  +1
range, upper    ``hi_j - dq - q_j``             ``-q'_j``    2                    -1
speed, lower    ``q'_j + V_j - dv``             (``q''_j``)  1 (``h' = q''_j``)   +1
speed, upper    ``V_j - dv - q'_j``             (``-q''_j``) 1                    -1
==============  ==============================  ===========  ==============  =====

so each barrier's highest derivative is ``sign * q''_j = sign * (q''_0,j + (M^-1 tau)_j)``:
the four share one model error, that of joint ``j``'s acceleration, and one learner serves
them (:class:`~afvsgp_gym.types.BarrierLayout`). Rows are ordered range barriers first
(lower, upper for joint 1, then joint 2, ...), then the speed barriers in the same order;
relative-degree-1 rows keep ``h`` in the first column of the derivatives (the second is 0).

A joint *violates* its limits, as the real controller would abort on, when it reaches its
range stop (``q_j <= lo_j`` or ``q_j >= hi_j``) or exceeds its speed (``|q'_j| > V_j``); the
optional checks add the acceleration limits (``|q''_j| > max_acceleration_j``, the
measured acceleration over a control period) and the torque-rate limit
(``|tau_j(t) - tau_j(t - dt)| / dt > max_torque_rate``, the commanded torques).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afvsgp_gym.types import BarrierLayout

__all__ = ["FRANKA_MAX_ACCELERATION", "FRANKA_MAX_SPEED", "FRANKA_MAX_TORQUE_RATE",
           "LIMIT_CALIBRATION_GATE", "LIMIT_CALIBRATION_STEP", "JointLimits", "arm_layout",
           "joint_projection", "limit_calibration"]

#: Franka datasheet joint speed limits (rad/s), joints 1-7.
FRANKA_MAX_SPEED = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
#: Franka datasheet joint acceleration limits (rad/s^2), joints 1-7.
FRANKA_MAX_ACCELERATION = np.array([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0])
#: Franka datasheet torque-rate limit (Nm/s), every joint.
FRANKA_MAX_TORQUE_RATE = 1000.0

#: The learned band's online correction suggested for the joint-limit barriers, by the Franka
#: envs and the robot bridge alike (docs: "Any policy", "Calibration"): their learned joint
#: accelerations are confidently wrong where a policy drives a joint through states its data
#: never covered (in closed loop the filter's torque follows the state, so the gain's error
#: hides in the bias term: after a swing of joint 4 its learned gain was 4x too small with a
#: std of 4 % of it). The range barriers (degree 2) take the additive margin (noise standard
#: deviations per miss, ``"conformal-additive"``); the speed barriers (degree 1), which have
#: no state to absorb one period's error and where the error grows with the torque, take the
#: multiplier (standard deviations per miss, ``"conformal"``), which scales the band with the
#: torque. The multiplier on the range barriers too made the program infeasible ~5x as often
#: and held joints on their stops. The obstacle pairs keep the paper's band.
LIMIT_CALIBRATION_STEP = 1.0
#: ... adapted only on the steps where a miss could decide the constraint (the margin at the
#: applied action below the band's width, ``calibration_gate``): ungated, the speed barriers
#: (always in the program) also counted misses far from their limit, the multipliers climbed
#: to 15-19 and held the joints' torque back for the rest of the episode, and the tracker
#: drifted away (tracking 3-4x worse in the episodes it hit).
LIMIT_CALIBRATION_GATE = True


def arm_layout(n_pairs: int, limits: JointLimits | None, projected: bool = False
               ) -> BarrierLayout:
    """The layout of ``n_pairs`` obstacle barriers (relative degree 2, one learner each)
    followed by the ``limits``' barriers (one learner per joint, their own hyperparameter
    group), as the Franka envs and the robot bridge order them. ``projected``: every pair
    projected onto the joints' learners instead (``learner = -1``; the shared learner, issue
    45), which needs the limits."""
    k = int(n_pairs)
    if limits is None:
        if projected:
            raise ValueError("the shared learner needs the joint-limit barriers (their "
                             "learners are the shared ones): limit_barriers=True")
        return BarrierLayout.uniform(k, 2)
    learner = np.concatenate([np.arange(k), k + limits.joint])
    group = np.ones(limits.n_joints, dtype=np.int64)
    if projected:
        learner = np.concatenate([np.full(k, -1), limits.joint])
    else:
        group = np.concatenate([np.zeros(k, dtype=np.int64), group])
    return BarrierLayout(np.concatenate([np.full(k, 2), limits.relative_degree]), learner,
                         np.concatenate([np.ones(k), limits.sign]), group)


def joint_projection(pair_rows: np.ndarray, limits: JointLimits) -> np.ndarray:
    """``(K, n_joints)``, read-only: every barrier's model error per joint-acceleration error
    (``BarrierSet.projection`` of :func:`arm_layout`'s projected layout): ``pair_rows`` (k,
    n_joints) = ``n' J_s`` for the obstacle pairs (``Delta h'' = n' J_s Delta q''``, the
    kinematics known), then ``sign`` on its own joint for each limit barrier."""
    k = len(pair_rows)
    out = np.zeros((k + limits.n_barriers, limits.n_joints))
    out[:k] = pair_rows
    out[k + np.arange(limits.n_barriers), limits.joint] = limits.sign
    out.flags.writeable = False
    return out


def limit_calibration(n_pairs: int, n_joints: int) -> dict:
    """The ``FilterConfig`` calibration options suggested for ``n_pairs`` obstacle barriers
    (the paper's band) followed by ``n_joints`` joints' limit barriers in
    :class:`JointLimits` order (the margin on the ranges, the multiplier on the speeds,
    :data:`LIMIT_CALIBRATION_STEP`, gated by :data:`LIMIT_CALIBRATION_GATE`)."""
    return {"calibration": (("off",) * n_pairs + ("conformal-additive",) * (2 * n_joints)
                            + ("conformal",) * (2 * n_joints)),
            "calibration_step": np.concatenate([np.zeros(n_pairs),
                                                np.full(4 * n_joints, LIMIT_CALIBRATION_STEP)]),
            "calibration_gate": LIMIT_CALIBRATION_GATE}


def _joint_array(value, n: int, name: str, positive: bool) -> np.ndarray:
    arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (n,)).copy()
    for j, v in enumerate(arr):
        if not math.isfinite(v) or (positive and not v > 0):
            what = "finite and > 0" if positive else "finite"
            raise ValueError(f"{name} of joint {j + 1} must be {what}. Got: {v!r}")
    return arr


@dataclass(frozen=True)
class JointLimits:
    """Joint ranges and speeds (and optionally accelerations and torque rate) of an arm.

    Parameters
    ----------
    lower, upper : array_like of shape (n,)
        Joint range (rad), ``lower < upper`` per joint.
    max_speed : array_like of shape (n,)
        ``V_j > 0`` (rad/s).
    range_margin, speed_margin : float
        Barrier margins inside the range (rad) and below the speed (rad/s), ``>= 0`` and
        smaller than half the range and the speed.
    max_acceleration : array_like of shape (n,) or None
        Checked only when given (rad/s^2).
    max_torque_rate : float or None
        Checked only when given (Nm/s).
    """

    lower: np.ndarray
    upper: np.ndarray
    max_speed: np.ndarray
    range_margin: float = 0.0
    speed_margin: float = 0.0
    max_acceleration: np.ndarray | None = None
    max_torque_rate: float | None = None

    def __post_init__(self) -> None:
        lo = np.ravel(np.asarray(self.lower, dtype=np.float64))
        n = len(lo)
        lo = _joint_array(lo, n, "lower", False)
        hi = _joint_array(self.upper, n, "upper", False)
        speed = _joint_array(self.max_speed, n, "max_speed", True)
        for j in np.flatnonzero(~(lo < hi)):
            raise ValueError(f"joint {j + 1}: lower ({lo[j]!r}) must be < upper ({hi[j]!r})")
        dq, dv = float(self.range_margin), float(self.speed_margin)
        if not (math.isfinite(dq) and 0 <= dq < 0.5 * float(np.min(hi - lo))):
            raise ValueError(f"range_margin must be >= 0 and below half of every joint's range. "
                             f"Got: {self.range_margin!r}")
        if not (math.isfinite(dv) and 0 <= dv < float(np.min(speed))):
            raise ValueError(f"speed_margin must be >= 0 and below every joint's max_speed. "
                             f"Got: {self.speed_margin!r}")
        acc = None if self.max_acceleration is None else _joint_array(
            self.max_acceleration, n, "max_acceleration", True)
        rate = self.max_torque_rate
        if rate is not None and not (math.isfinite(float(rate)) and float(rate) > 0):
            raise ValueError(f"max_torque_rate must be > 0 or None. Got: {rate!r}")
        for name, value in (("lower", lo), ("upper", hi), ("max_speed", speed),
                            ("range_margin", dq), ("speed_margin", dv),
                            ("max_acceleration", acc),
                            ("max_torque_rate", None if rate is None else float(rate))):
            object.__setattr__(self, name, value)
        self_joint = np.tile(np.repeat(np.arange(n), 2), 2)
        object.__setattr__(self, "joint", self_joint)
        object.__setattr__(self, "sign", np.tile([1.0, -1.0], 2 * n))

    @property
    def n_joints(self) -> int:
        return int(self.lower.shape[0])

    @property
    def n_barriers(self) -> int:
        """Four per joint."""
        return 4 * self.n_joints

    @property
    def relative_degree(self) -> np.ndarray:
        """(4n,): 2 for the range barriers, 1 for the speed barriers."""
        n = self.n_joints
        return np.concatenate([np.full(2 * n, 2), np.full(2 * n, 1)])

    def names(self) -> tuple[str, ...]:
        n = self.n_joints
        out = [f"joint{j + 1}/{side}" for j in range(n) for side in ("range_min", "range_max")]
        return tuple(out + [f"joint{j + 1}/{side}" for j in range(n)
                            for side in ("speed_min", "speed_max")])

    def derivatives(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """``[h, h']`` (4n, 2) of every barrier (``[h, 0]`` for the speed barriers)."""
        n = self.n_joints
        out = np.zeros((4 * n, 2))
        out[0 : 2 * n : 2, 0] = q - self.lower - self.range_margin
        out[1 : 2 * n : 2, 0] = self.upper - self.range_margin - q
        out[0 : 2 * n : 2, 1] = qd
        out[1 : 2 * n : 2, 1] = -qd
        top = self.max_speed - self.speed_margin
        out[2 * n :: 2, 0] = qd + top
        out[2 * n + 1 :: 2, 0] = top - qd
        return out

    def features(self, q: np.ndarray, qd: np.ndarray, feature_dim: int) -> np.ndarray:
        """``xi`` (4n, feature_dim) = ``[q, q', 0, ...]`` for every barrier: the state that
        joint accelerations depend on (all four barriers of a joint share it)."""
        n = self.n_joints
        xi = np.zeros((4 * n, feature_dim))
        xi[:, :n] = q
        xi[:, n : 2 * n] = qd
        return xi

    def terms(self, acceleration: np.ndarray, gain: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``lf`` (4n,) and ``lg`` (4n, m) from the joint accelerations at zero action
        ``acceleration`` (n,) and their gain ``gain`` (n, m) (``q'' = acceleration + gain
        u``): ``sign * q''_j``."""
        sign = self.sign
        return sign * acceleration[self.joint], sign[:, None] * gain[self.joint]

    def violation(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray | None = None,
                  torque_rate: np.ndarray | None = None) -> bool:
        """True when some joint is at its range stop or above its speed, or (optional
        checks, when the limits and the values are given) above its acceleration or the
        torque rate."""
        if np.any(q <= self.lower) or np.any(q >= self.upper):
            return True
        if np.any(np.abs(qd) > self.max_speed):
            return True
        if self.max_acceleration is not None and qdd is not None:
            if np.any(np.abs(qdd) > self.max_acceleration):
                return True
        if self.max_torque_rate is not None and torque_rate is not None:
            if np.any(np.abs(torque_rate) > self.max_torque_rate):
                return True
        return False
