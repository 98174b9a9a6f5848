"""Task-space PD tracking controller that ignores obstacles (the filter's u_nom)."""

from __future__ import annotations

from typing import Any

import numpy as np


class NominalController:
    """Callable policy ``obs -> action`` tracking the reference in the observation.

    Point mass: ``u = (m_hat (r'' + kp e + kd e') + c_hat p') / max_force`` with the nominal
    model's mass and drag when it has them ("perturbed", "exact"), else ``nominal_mass`` and
    zero drag (a gain scale only). Franka: see ``afvsgp_gym.envs.franka`` (task-space PD with
    Jacobian transpose, joint damping and a null-space posture term, plus the nominal
    model's inertia when it has one). The output is clipped to the action bounds.

    Parameters
    ----------
    env : gymnasium.Env
        A (possibly wrapped) afvsgp_gym environment; only ``env.unwrapped`` is read.
    kp, kd : float, optional
        Task-space stiffness (1/s^2) and damping (1/s); defaults depend on the environment.
    """

    def __init__(self, env: Any, kp: float | None = None, kd: float | None = None) -> None:
        base = env.unwrapped
        self.low = np.asarray(env.action_space.low, dtype=np.float64)
        self.high = np.asarray(env.action_space.high, dtype=np.float64)
        if hasattr(base, "make_nominal_policy"):
            self._impl = base.make_nominal_policy(kp=kp, kd=kd)
        else:
            self._impl = _PointMassPD(base, kp, kd)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        u = self._impl(np.asarray(obs, dtype=np.float64))
        return np.clip(u, self.low, self.high).astype(np.float32)


class _PointMassPD:
    def __init__(self, env: Any, kp: float | None, kd: float | None) -> None:
        self.kp = 25.0 if kp is None else float(kp)
        self.kd = 10.0 if kd is None else float(kd)
        self.d = env.dim
        self.n = env.n_obstacles
        if env.nominal_model in ("perturbed", "exact"):
            params = env.model_parameters("nominal")
        else:
            params = {"mass": env.nominal_mass, "drag": 0.0}
        self.mass, self.drag = params["mass"], params["drag"]
        self.max_force = env.max_force

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        d = self.d
        p, v = obs[:d], obs[d : 2 * d]
        k = 2 * d + 2 * self.n * d
        r, rd, rdd = obs[k : k + d], obs[k + d : k + 2 * d], obs[k + 2 * d : k + 3 * d]
        acc = rdd + self.kp * (r - p) + self.kd * (rd - v)
        return (self.mass * acc + self.drag * v) / self.max_force
