"""The share of a brake's damping that the torque limits admit (numpy only, no simulator).

Both brakes of the package (the Franka envs' :meth:`backup_action` and the robot bridge's
:class:`~afvsgp_gym.robots.bridge.Brake`) damp with ``tau = c + s M (-2 w q')`` beyond the
torque limits: the largest share ``s`` in [0, 1] that keeps every joint within its limit,
so the commanded joint accelerations keep their direction (clipping each joint's torque
apart bends them through the coupled inertia).
"""

from __future__ import annotations

import numpy as np

__all__ = ["admissible_share"]


def admissible_share(base: np.ndarray, step: np.ndarray, bound) -> float:
    """The largest ``s`` in [0, 1] with ``|base + s step| <= bound`` for every component
    where ``base`` itself is within the bound (0 where it is not).

    Example:
        >>> admissible_share(np.array([0.5, 0.0]), np.array([1.0, -4.0]), 1.0)
        0.25
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        room = np.where(step > 0, (bound - base) / step,
                        np.where(step < 0, (-bound - base) / step, np.inf))
    return min(1.0, max(0.0, float(room.min())))
