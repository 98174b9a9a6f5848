"""A tiny 2-D double integrator with one circular obstacle (independent of afvsgp_gym.envs)."""

import numpy as np
import pytest

from afvsgp_gym.types import BarrierTerms


class Disc:
    """p'' = gain * u + wind(p); h = |p - c| - R (relative degree 2). Nominal: gain0, no wind."""

    def __init__(self, gain=0.5, gain0=1.0, wind=(0.0, 0.0), dt=0.02, substeps=20):
        self.gain, self.gain0, self.wind = gain, gain0, np.asarray(wind, float)
        self.dt, self.substeps = dt, substeps
        self.c, self.R = np.array([0.0, 0.0]), 0.3
        self.p, self.v = np.array([-1.0, 0.02]), np.zeros(2)

    def accel(self, p, u, true=True):
        w = self.wind * (1.0 + 0.5 * np.sin(p[0] * 3)) if true else 0.0
        return (self.gain if true else self.gain0) * u + w

    def terms(self, model="nominal"):
        d = self.p - self.c
        r = np.linalg.norm(d)
        n = d / r
        hd = n @ self.v
        curv = (self.v @ self.v - hd**2) / r
        true = model == "true"
        lf = curv + n @ (self.accel(self.p, np.zeros(2), true))
        lg = n * (self.gain if true else self.gain0)
        xi = np.concatenate([d, self.v])
        return [BarrierTerms(np.array([r - self.R, hd]), float(lf), lg, xi)]

    def step(self, u):
        h = self.dt / self.substeps
        for _ in range(self.substeps):  # semi-implicit Euler, fine substeps
            self.v = self.v + h * self.accel(self.p, u)
            self.p = self.p + h * self.v
        return self.terms()[0].h

    def nominal(self, goal=(1.0, 0.0)):
        return np.clip(4.0 * (np.asarray(goal) - self.p) - 3.0 * self.v, -1, 1)


@pytest.fixture
def disc():
    return Disc
