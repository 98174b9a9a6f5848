"""A Kalman filter on the obstacles a camera sees: noisy, delayed samples of each centre in,
position, velocity, acceleration and their covariance at the control time out (numpy only).

The camera samples obstacle ``i``'s centre at ``t_s`` with noise ``N(0, sigma^2 I_3)``
(``sigma`` = ``measurement_std``, m) and the sample arrives later; :meth:`ObstacleEstimator.update`
fuses it *at its sample time* and :meth:`ObstacleEstimator.predict` carries the estimate forward
to the control time ``t``, which compensates the delay. The three axes are independent and
modelled alike, so one per-axis state ``x = [p, v]`` (``"constant-velocity"``) or
``x = [p, v, a]`` (``"constant-acceleration"``), of size ``s``, per axis and one per-axis
covariance ``P`` (s, s) per obstacle serve x, y and z (the full covariance is ``P kron I_3``).

Process models (Bar-Shalom, Li and Kirubarajan, *Estimation with Applications to Tracking and
Navigation*, 2001, sec. 6.2.2 and 6.2.3): continuous white noise of spectral density
``q = process_std^2`` on the acceleration (constant velocity, m^2 s^-3) or on the jerk
(constant acceleration, m^2 s^-5), discretised exactly over ``dt``:

- constant velocity: ``F = [[1, dt], [0, 1]]``,
  ``Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]``;
- constant acceleration: ``F = [[1, dt, dt^2/2], [0, 1, dt], [0, 0, 1]]``,
  ``Q = q [[dt^5/20, dt^4/8, dt^3/6], [dt^4/8, dt^3/3, dt^2/2], [dt^3/6, dt^2/2, dt]]``;

in general ``F_ij = dt^(j-i) / (j-i)!`` (``j >= i``) and
``Q_ij = q dt^m / (m (s-1-i)! (s-1-j)!)`` with ``m = 2s - 1 - i - j``
(:func:`transition`, :func:`discrete_process_noise`).

Measurement ``z = p + noise``, ``H = [1, 0(, 0)]``, ``R = sigma^2``. Prediction
``x <- F x``, ``P <- F P F^T + Q``; update with the innovation ``y = z - H x``,
``S = H P H^T + R = P_00 + R`` (one scalar per obstacle for all three axes),
``K = P H^T / S``, ``x <- x + K y`` and, in Joseph form,
``P <- (I - K H) P (I - K H)^T + R K K^T``; ``P`` is symmetrised after every step. The first
sample of an obstacle sets ``p = z``, ``v = 0`` (``a = 0``) and
``P = diag(sigma^2, initial_velocity_std^2[, initial_acceleration_std^2])`` (the exact
posterior under a flat prior on ``p`` and that prior on ``v``, ``a``).
"""

from __future__ import annotations

import math

import numpy as np

from afvsgp_gym.validation import check_real

__all__ = ["ESTIMATOR_MODELS", "TIME_TOLERANCE", "ObstacleEstimator", "discrete_process_noise",
           "transition"]

#: Values of ``ObstacleEstimator(model=...)``.
ESTIMATOR_MODELS = ("constant-velocity", "constant-acceleration")

#: How far (s) the control time may fall before the last fused sample time and still be taken
#: as that time: rounding of times built from different sums, not a real earlier time.
TIME_TOLERANCE = 1e-9


def _state_size(model: str) -> int:
    if model not in ESTIMATOR_MODELS:
        raise ValueError(f"model must be one of {ESTIMATOR_MODELS}. Got: {model!r}")
    return ESTIMATOR_MODELS.index(model) + 2


def _coefficients(s: int) -> tuple[np.ndarray, np.ndarray]:
    """Tables ``(F_coef, Q_coef)`` of shapes (s, s*s) and (2s, s*s): ``F = dt^k F_coef[k]``
    and ``Q / q = dt^k Q_coef[k]`` summed over the powers ``k``."""
    f = np.zeros((s, s, s))
    g = np.zeros((2 * s, s, s))
    for i in range(s):
        for j in range(s):
            if j >= i:
                f[j - i, i, j] = 1.0 / math.factorial(j - i)
            m = 2 * s - 1 - i - j
            g[m, i, j] = 1.0 / (m * math.factorial(s - 1 - i) * math.factorial(s - 1 - j))
    return f.reshape(s, s * s), g.reshape(2 * s, s * s)


_COEFFICIENTS = {s: _coefficients(s) for s in (2, 3)}
_EXPONENTS = {s: np.arange(2 * s) for s in (2, 3)}


def _models(dt: np.ndarray, s: int, q: float) -> tuple[np.ndarray, np.ndarray]:
    """``F`` and ``Q`` (n, s, s) for the steps ``dt`` (n,) of a model of state size ``s``."""
    f, g = _COEFFICIENTS[s]
    powers = dt[:, None] ** _EXPONENTS[s]
    n = len(dt)
    return ((powers[:, :s] @ f).reshape(n, s, s),
            (q * (powers @ g)).reshape(n, s, s))


def _check_dt(dt) -> float:
    return check_real(dt, "dt", low=0.0)


def _positive(value, name: str) -> float:
    return check_real(value, name, low=0.0, low_open=True)


def transition(dt: float, model: str) -> np.ndarray:
    """The per-axis transition ``F`` (s, s) over ``dt >= 0`` s (module docstring)."""
    s = _state_size(model)
    return _models(np.array([_check_dt(dt)]), s, 0.0)[0][0]


def discrete_process_noise(dt: float, process_std: float, model: str) -> np.ndarray:
    """The per-axis process noise ``Q`` (s, s) over ``dt >= 0`` s, the exact discretisation of
    white acceleration (constant velocity) or jerk (constant acceleration) of spectral density
    ``process_std^2`` (module docstring)."""
    s = _state_size(model)
    try:
        w = float(process_std)
    except (TypeError, ValueError):
        raise ValueError(f"process_std must be finite and >= 0. Got: {process_std!r}") from None
    if not (math.isfinite(w) and w >= 0.0):
        raise ValueError(f"process_std must be finite and >= 0. Got: {process_std!r}")
    return _models(np.array([_check_dt(dt)]), s, w * w)[1][0]


def _symmetric(p: np.ndarray) -> np.ndarray:
    return 0.5 * (p + p.transpose(0, 2, 1))


class ObstacleEstimator:
    """Kalman filter on ``n_obstacles`` obstacle centres, the axes independent and alike
    (module docstring).

    Parameters
    ----------
    n_obstacles : int
        ``O >= 1``.
    measurement_std : float
        ``sigma > 0`` (m), the camera's noise per axis (a camera without noise takes no
        estimator; a tiny positive value is fine).
    process_std : float
        ``sqrt(q) > 0``: white acceleration (m s^-1.5, constant velocity) or white jerk
        (m s^-2.5, constant acceleration).
    model : str
        One of :data:`ESTIMATOR_MODELS`.
    initial_velocity_std, initial_acceleration_std : float
        Prior standard deviations (> 0) of the velocity (m/s) and, for constant acceleration,
        the acceleration (m/s^2) at an obstacle's first sample.
    """

    def __init__(self, n_obstacles: int, measurement_std: float, process_std: float = 1.0,
                 model: str = "constant-velocity", initial_velocity_std: float = 0.5,
                 initial_acceleration_std: float = 2.0):
        if (isinstance(n_obstacles, bool) or not isinstance(n_obstacles, (int, np.integer))
                or n_obstacles < 1):
            raise ValueError(f"n_obstacles must be an integer >= 1. Got: {n_obstacles!r}")
        self.n_obstacles = int(n_obstacles)
        self.measurement_std = _positive(measurement_std, "measurement_std")
        self.process_std = _positive(process_std, "process_std")
        self.state_size = _state_size(model)
        self.model = model
        self.initial_velocity_std = _positive(initial_velocity_std, "initial_velocity_std")
        self.initial_acceleration_std = _positive(initial_acceleration_std,
                                                  "initial_acceleration_std")
        s = self.state_size
        self._q = self.process_std ** 2
        self._r = self.measurement_std ** 2
        self._p0 = np.diag([self._r, self.initial_velocity_std ** 2,
                            self.initial_acceleration_std ** 2][:s])
        self._eye = np.eye(s)
        self.reset()

    def reset(self) -> None:
        """Forget every measurement."""
        o, s = self.n_obstacles, self.state_size
        self._x = np.zeros((o, s, 3))
        self._p = np.zeros((o, s, s))
        self._t = np.full(o, -np.inf)

    @property
    def initialized(self) -> bool:
        """True once every obstacle has had a measurement."""
        return bool(np.isfinite(self._t).all())

    @property
    def last_sample_time(self) -> np.ndarray:
        """The sample time (s) of each obstacle's last fused measurement (O,), ``-inf`` before
        its first."""
        return self._t.copy()

    def _propagate(self, x: np.ndarray, p: np.ndarray,
                   dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``F x`` and ``F P F^T + Q`` over the steps ``dt`` (n,)."""
        f, q = _models(dt, self.state_size, self._q)
        return f @ x, _symmetric(f @ p @ f.transpose(0, 2, 1) + q)

    def _times(self, t, name: str) -> np.ndarray:
        try:
            arr = np.asarray(t, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a number or an array of shape "
                             f"({self.n_obstacles},). Got: {t!r}") from None
        if arr.ndim == 0:
            return np.full(self.n_obstacles, float(arr))
        if arr.shape != (self.n_obstacles,):
            raise ValueError(f"{name} must be a number or an array of shape "
                             f"({self.n_obstacles},). Got shape {arr.shape}")
        return arr

    def update(self, positions: np.ndarray, sample_time: float | np.ndarray) -> None:
        """Fuse one measurement per obstacle.

        Parameters
        ----------
        positions : ndarray, shape (O, 3)
            Measured centres (m); a row with a NaN is no measurement of that obstacle.
        sample_time : float or ndarray of shape (O,)
            When they were taken (s), finite where the row is measured. A sample no newer than
            the obstacle's last fused one is ignored (out of order or a repeat). An
            obstacle's first sample initialises it (module docstring).
        """
        z = np.asarray(positions, dtype=np.float64)
        if z.shape != (self.n_obstacles, 3):
            raise ValueError(f"positions must be an array of shape ({self.n_obstacles}, 3). "
                             f"Got shape {z.shape}")
        ts = self._times(sample_time, "sample_time")
        if np.isfinite(z).all():                    # the common case: every row measured
            if not np.isfinite(ts).all():
                raise ValueError(f"sample_time must be finite where positions has a "
                                 f"measurement. Got: {sample_time!r}")
            newer = ts > self._t
        else:
            present = ~np.isnan(z).any(axis=1)
            if not np.isfinite(z[present]).all():
                raise ValueError(f"positions must be finite or NaN (a missing row). "
                                 f"Got: {z!r}")
            if not np.isfinite(ts[present]).all():
                raise ValueError(f"sample_time must be finite where positions has a "
                                 f"measurement. Got: {sample_time!r}")
            with np.errstate(invalid="ignore"):
                newer = present & (ts > self._t)
        if not newer.any():
            return
        first = newer & np.isinf(self._t)
        if first.any():
            self._x[first] = 0.0
            self._x[first, 0] = z[first]
            self._p[first] = self._p0
        fuse = newer & ~first
        if fuse.any():
            idx = np.flatnonzero(fuse)
            x, p = self._propagate(self._x[idx], self._p[idx], ts[idx] - self._t[idx])
            gain = p[:, :, 0] / (p[:, 0, 0] + self._r)[:, None]           # K (n, s)
            x += gain[:, :, None] * (z[idx] - x[:, 0])[:, None, :]
            a = np.broadcast_to(self._eye, p.shape).copy()                # I - K H
            a[:, :, 0] -= gain
            p = a @ p @ a.transpose(0, 2, 1) + self._r * gain[:, :, None] * gain[:, None, :]
            self._x[idx] = x
            self._p[idx] = _symmetric(p)
        self._t[newer] = ts[newer]

    def predict(self, t: float | np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The estimate at the control time ``t`` (s; a number or one per obstacle, no earlier
        than each obstacle's last sample time, up to :data:`TIME_TOLERANCE`). Leaves the
        filter as it is.

        Returns
        -------
        position, velocity, acceleration : ndarray, shape (O, 3)
            The acceleration is 0 for constant velocity.
        covariance : ndarray, shape (O, 3, 3)
            The per-axis covariance of ``[p, v, a]`` (for constant velocity the ``a`` row and
            column are 0).

        Raises
        ------
        RuntimeError
            If some obstacle has had no measurement.
        ValueError
            If ``t`` is not finite or earlier than a last sample time.
        """
        if not self.initialized:
            missing = np.flatnonzero(np.isinf(self._t)).tolist()
            raise RuntimeError(f"predict() before a measurement of obstacle(s) {missing}: "
                               f"call update() first")
        ts = self._times(t, "t")
        dt = ts - self._t
        if not (dt >= -TIME_TOLERANCE).all():     # also catches NaN
            raise ValueError(f"t must be finite and >= each obstacle's last sample time "
                             f"{self._t.tolist()}. Got: {t!r}")
        if not np.isfinite(dt).all():
            raise ValueError(f"t must be finite. Got: {t!r}")
        x, p = self._propagate(self._x, self._p, np.maximum(dt, 0.0))
        o, s = self.n_obstacles, self.state_size
        acceleration = x[:, 2].copy() if s == 3 else np.zeros((o, 3))
        if s == 3:
            covariance = p
        else:
            covariance = np.zeros((o, 3, 3))
            covariance[:, :2, :2] = p
        return x[:, 0].copy(), x[:, 1].copy(), acceleration, covariance
