"""Exploration noise added to the proposal of a learning filter (Algorithm 1).

During warm-up the proposal gets Gaussian noise of std ``warmup_noise`` (a fraction of the
half range of the action bounds) so the action gain becomes identifiable. After warm-up
noise of std up to ``online_noise`` is added only where it is needed (the controller decides:
a barrier in the program whose learned model is uncertain at the proposal, the std scaled by
how uncertain its action gain is); a safe proposal with a confident model passes unchanged.
The noisy proposal is then filtered, so the constraints still hold.
"""

from __future__ import annotations

import math

import numpy as np

from afvsgp_gym import _compiled
from afvsgp_gym.cbf.fastpath import clip

__all__ = ["Exploration", "exploration_scale", "relative_gain_uncertainty"]

_step = _compiled.extension("step")


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

    @property
    def half_range(self) -> np.ndarray:
        """(m,) half range of the action bounds (the unit of the noise)."""
        return self._half_range

    def perturb(self, u: np.ndarray, warm: bool, scale: float = 1.0) -> np.ndarray:
        """``clip(u + noise)``, the online noise's std multiplied by ``scale`` clipped to
        [0, 1] (NaN counts as 1); ``u`` unchanged when the noise is 0 or ``u`` is not finite."""
        scale = max(scale, 0.0) if scale < 1.0 else 1.0  # NaN fails the comparison: 1
        std = self.warmup_noise if warm else self.online_noise * scale
        if std <= 0 or not math.isfinite(float(u.sum())):
            return u
        noisy = u + std * self._half_range * self._rng.standard_normal(u.shape[0])
        return clip(noisy, self.low, self.high)


def relative_gain_uncertainty(sigma: np.ndarray, gain: np.ndarray,
                              half_range: np.ndarray) -> np.ndarray:
    """``rho_k = sqrt(trace(H Sigma_uu,k H)) / ||H a_k||`` per barrier: the predicted standard
    deviation of the learned action gain against the gain itself, both over the action
    bounds (``H = diag(half_range)``, ``Sigma_uu`` the action block of the eq. 51 covariance
    ``sigma`` (k, m+1, m+1), ``a`` (k, m) the constraint's gradient in the action). ``inf``
    where the gain is zero (nothing known), NaN where the inputs are not finite."""
    var = np.einsum("kii,i->k", sigma[:, 1:, 1:], half_range * half_range)
    scaled = gain * half_range
    norm = np.sqrt(np.add.reduce(scaled * scaled, axis=1))  # np.linalg.norm's arithmetic
    if 0.0 < norm.min() and norm.max() < math.inf:
        return np.sqrt(np.maximum(var, 0.0)) / norm
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(np.maximum(var, 0.0)) / norm


def exploration_scale(sigma: np.ndarray, a0: np.ndarray, a: np.ndarray, u_nom: np.ndarray,
                      low: np.ndarray, high: np.ndarray, noise_std: np.ndarray,
                      half_range: np.ndarray, threshold: float, reach: float,
                      backend: str | _compiled.Backend = "auto") -> float:
    """The scale of the online exploration noise at the proposal ``u_nom``, or -1.0 for none.

    With ``u = clip(u_nom)`` and ``ubar = [1, u]``, barrier ``k`` (``sigma`` (k, m+1, m+1) its
    eq. 51 covariance, ``a0 + a u`` its mean margin) is gated when its predicted standard
    deviation ``std_k = sqrt(ubar' Sigma_k ubar)`` exceeds ``threshold`` noise standard
    deviations ``noise_std`` and the mean margin is below ``reach std_k``. The answer is the
    largest :func:`relative_gain_uncertainty` among the gated barriers (NaN if one is NaN),
    -1.0 when none is gated. In the compiled step glue unless ``backend`` is ``"numpy"``
    (:mod:`afvsgp_gym._compiled`)."""
    n, m = np.shape(a)
    if _compiled.resolve(backend, ("step",)).step and n and m + 1 <= 17:
        arrays = (sigma, a0, a, u_nom, low, high, noise_std, half_range)
        try:  # as they are when C-ordered float64 (the controller's), else converted
            return _step.exploration_scale(n, m, *arrays, float(threshold), float(reach))
        except ValueError:
            arrays = [np.ascontiguousarray(x, dtype=np.float64) for x in arrays]
        return _step.exploration_scale(n, m, *arrays, float(threshold), float(reach))
    u = clip(u_nom, low, high)
    ubar = np.concatenate([[1.0], u])
    std = np.sqrt(np.maximum(((sigma @ ubar) * ubar).sum(axis=1), 0.0))
    gated = np.flatnonzero((std > threshold * noise_std) & (a0 + a @ u < reach * std))
    if not len(gated):
        return -1.0
    return float(relative_gain_uncertainty(sigma[gated], a[gated], half_range).max())
