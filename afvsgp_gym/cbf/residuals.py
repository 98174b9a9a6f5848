"""Residual observer: a disturbance observer on top of the learned model error.

After each step the eq. 48 measurement ``z_k`` is compared with the learned mean the filter
used for barrier ``k``, ``e_k = z_k - b_k' ubar``, and ``bias_k <- (1 - w) bias_k + w e_k``
is added to that barrier's mean in the next constraints (eq. 05). A learner that is wrong in a
persistent direction (the drift or the action gain changed faster than the posterior adapts)
is corrected within ~1/w steps; zero-mean errors average out. A barrier that was not predicted
in a step (outside the cone program) restarts from zero bias.
"""

from __future__ import annotations

import numpy as np

from afvsgp_gym import _compiled

__all__ = ["ResidualObserver"]

_step = _compiled.extension("step")


class ResidualObserver:
    """Exponential average of the measured minus the predicted ``Delta B^(r)`` per barrier
    (the update from ``z`` in the compiled step glue unless ``backend`` is ``"numpy"``)."""

    def __init__(self, n_barriers: int, weight: float,
                 backend: str | _compiled.Backend = "auto"):
        self.weight = float(weight)
        self.bias = np.zeros(int(n_barriers))
        self.backend = _compiled.resolve(backend, ("step",))

    def reset(self) -> None:
        """Forget the bias (e.g. at an episode reset: the state jumps)."""
        self.bias[:] = 0.0

    def update(self, rows: np.ndarray, predicted: np.ndarray,
               measured: np.ndarray | None = None, *, z: np.ndarray | None = None) -> None:
        """``predicted`` and ``measured`` (len(rows),) for the (distinct) barriers ``rows`` of
        the step just taken, or ``z`` (K,) the measurements of every barrier in place of
        ``measured = z[rows]``; every other barrier's bias returns to 0. NaN measurements leave
        the bias."""
        if z is not None:
            if self.backend.step:
                try:
                    _step.residual_update(len(self.bias), len(rows), self.bias, rows,
                                          predicted, z, self.weight)
                    return
                except ValueError:  # arrays the core does not take: numpy
                    pass
            measured = z[rows]
        keep = np.zeros(self.bias.shape, dtype=bool)
        if self.weight > 0 and len(rows):
            e = measured - predicted
            ok = np.isfinite(e)
            r = rows[ok]
            self.bias[r] += self.weight * (e[ok] - self.bias[r])
        keep[rows] = True
        self.bias[~keep] = 0.0
