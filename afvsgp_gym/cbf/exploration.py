"""Exploration noise added to the proposal of a learning filter (Algorithm 1).

During warm-up the proposal gets Gaussian noise of std ``warmup_noise`` (a fraction of the
half range of the action bounds) so the action gain becomes identifiable. After warm-up a
smaller ``online_noise`` is added only where it is needed (the controller decides: a barrier
in the program whose learned model is uncertain at the proposal); a safe proposal with a
confident model passes unchanged. The noisy proposal is then filtered, so the constraints
still hold.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["Exploration"]


class Exploration:
    """Seeded Gaussian exploration on top of the proposal (clipped to the bounds)."""

    def __init__(self, low: np.ndarray, high: np.ndarray, warmup_noise: float,
                 online_noise: float, seed: int | None = None):
        self.low, self.high = low, high
        self._half_range = 0.5 * (high - low)
        self.warmup_noise = float(warmup_noise)
        self.online_noise = float(online_noise)
        self._rng = np.random.default_rng(seed)

    def reseed(self, seed: int) -> None:
        """A fresh stream derived from ``seed`` (reproducible episodes)."""
        self._rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5AFE]))

    def perturb(self, u: np.ndarray, warm: bool) -> np.ndarray:
        """``clip(u + noise)``; ``u`` unchanged when the noise is 0 or ``u`` is not finite."""
        std = self.warmup_noise if warm else self.online_noise
        if std <= 0 or not math.isfinite(float(u.sum())):
            return u
        noisy = u + std * self._half_range * self._rng.standard_normal(u.shape[0])
        return np.clip(noisy, self.low, self.high)
