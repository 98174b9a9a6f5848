"""The filter's view of the obstacles: a Kalman estimate from the env's camera, or its raw
reading taken as the truth (the baseline)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from afvsgp_gym.cbf.estimation import ObstacleEstimator
from afvsgp_gym.types import BarrierSet
from afvsgp_gym.validation import check_choice, check_real

__all__ = ["OBSTACLE_ESTIMATORS", "ObstacleTracking"]

#: Values of ``SafetyFilter(obstacle_estimator=...)``: ``"auto"`` is ``"kalman"`` on an env
#: with a camera and ``"raw"`` otherwise; ``"kalman"`` a constant-velocity and
#: ``"kalman-ca"`` a constant-acceleration Kalman filter; ``"raw"`` the env's reading as the
#: truth (no estimate, no sensing covariance in the constraints).
OBSTACLE_ESTIMATORS = ("auto", "kalman", "kalman-ca", "raw")

#: The smallest measurement noise the estimator assumes (m): a camera without noise but with
#: a slow rate or a delay still gets a well-posed filter.
MIN_MEASUREMENT_STD = 1e-4


class ObstacleTracking:
    """Estimate the obstacles from ``base``'s camera each control period and hand the
    estimate (with its covariance) to ``base.set_obstacle_estimate``; with ``"raw"`` strip
    the sensing covariance from the terms instead (the filter then trusts what it reads).

    Parameters
    ----------
    base : env
        The unwrapped env (its ``perception``, ``obstacle_reading``, ``set_obstacle_estimate``
        and ``time``, when it has a camera).
    estimator : str
        One of :data:`OBSTACLE_ESTIMATORS`.
    process_std : float
        The estimator's process noise (white acceleration, m s^-1.5, constant velocity; white
        jerk for constant acceleration). The default 0.03 is the smallest whose estimate is
        consistent on the scenarios' obstacles (accelerations up to ~0.1 m/s^2): normalised
        error squared 0.44-0.74 per degree of freedom, while they move too, at 1-2 cm, 30-250
        Hz and 0-100 ms (0.01: 3.3-4.8 while they move, overconfident). A livelier obstacle
        needs more; more widens the band (0.1 triples the velocity std, ~6 cm/s at 2 cm,
        30 Hz, 100 ms, which backs a constraint off by ~1.5 m/s^2).
    """

    def __init__(self, base: Any, estimator: str = "auto", process_std: float = 0.03):
        check_choice("obstacle_estimator", estimator, OBSTACLE_ESTIMATORS)
        process_std = check_real(process_std, "estimator_process_std", low=0.0, low_open=True)
        perception = getattr(base, "perception", None)
        camera = perception is not None and perception.camera
        if estimator == "auto":
            estimator = "kalman" if camera else "raw"
        self.name = estimator
        self.raw = estimator == "raw"
        self._held_at: float | None = None  # the time of the estimate last set
        self.estimator = None
        if not self.raw and camera:
            model = "constant-acceleration" if estimator == "kalman-ca" else "constant-velocity"
            self.estimator = ObstacleEstimator(
                base.n_obstacles, max(perception.obstacle_noise, MIN_MEASUREMENT_STD),
                process_std=process_std, model=model)

    def reset(self) -> None:
        self._held_at = None
        if self.estimator is not None:
            self.estimator.reset()

    def sense(self, base: Any) -> None:
        """Fuse the camera's newest sample and set the estimate for the current period (left
        as :meth:`hold` set it when no new sample arrived: the same prediction)."""
        if self.estimator is None:
            return
        position, sample_time = base.obstacle_reading()
        fused = self.estimator.last_sample_time
        self.estimator.update(position, sample_time)
        if self._held_at == base.time and np.array_equal(fused, self.estimator.last_sample_time):
            return
        self.hold(base)

    def hold(self, base: Any) -> None:
        """Set the estimate predicted to the current period *without* fusing a new sample:
        the terms after a step for the eq. 48 sample, so that the learners see the arm's
        model error and not the jump of a measurement update (at 30 Hz a 1 cm innovation
        moves the estimated velocity by centimetres per second within one 4 ms period, a
        spurious ``h''`` of metres per second squared)."""
        if self.estimator is None or not self.estimator.initialized:
            return
        p, v, a, cov = self.estimator.predict(base.time)
        base.set_obstacle_estimate(p, v, a, cov)
        self._held_at = base.time

    def terms(self, terms: BarrierSet) -> BarrierSet:
        """``terms`` as the filter takes them (the raw baseline: without covariance)."""
        if self.raw and terms.covariance is not None:
            return replace(terms, covariance=None)
        return terms
