"""Task-space PD tracking controller that ignores obstacles (the filter's u_nom)."""

from __future__ import annotations

from typing import Any

import numpy as np


class NominalController:
    """Callable policy ``obs -> action`` tracking the reference in the observation.

    Point mass: ``u = (m_hat (r'' + kp e + kd e') + c_hat p') / max_force`` with the nominal
    model's mass and drag when it has them ("perturbed", "exact"), else ``nominal_mass`` and
    zero drag (a gain scale only).

    Franka, nominal model "perturbed"/"exact": inverse dynamics of that model for the joint
    acceleration ``q''_d = J^+ (r'' + kp e + kd e' - J' q') + N (posture PD)`` (kp = 100 1/s^2,
    kd = 20 1/s). Nominal "zero"/"kinematic" (no dynamics known): Jacobian-transpose PD
    ``tau = J' (kp e + kd e') + N' (posture PD)`` with kp = 600 N/m, kd = 50 N s/m; only the
    (known) kinematics are used. Posture PD towards the ready pose in the null space keeps the
    redundant arm away from joint limits. The output is clipped to the action bounds.

    Franka reach (velocity command): straight at the goal, ``u = clip(kp (g - p) / v_max)``
    with kp = 6 1/s, blind to the obstacles.

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
        if hasattr(base, "goal") and hasattr(base, "loop"):
            self._impl = _ReachStraight(base, kp)
        elif hasattr(base, "model") and hasattr(base, "q_home"):
            self._impl = _FrankaTaskPD(base, kp, kd)
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


class _ReachStraight:
    """Straight-line velocity command at the goal for FrankaObstacleReachEnv."""

    def __init__(self, env: Any, kp: float | None) -> None:
        self.kp = 6.0 if kp is None else float(kp)
        self.max_speed = env.loop.max_speed

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.kp * obs[23:26] / self.max_speed


class _FrankaTaskPD:
    """Task-space tracking for FrankaObstacleEnv (see NominalController)."""

    def __init__(self, env: Any, kp: float | None, kd: float | None) -> None:
        import mujoco

        self._mj = mujoco
        self.dynamic = env.nominal_model in ("perturbed", "exact")
        # kinematics are known in every mode; dynamics only in perturbed/exact
        self.model = env.nominal_mj_model if self.dynamic else env.model
        self.data = mujoco.MjData(self.model)
        self.site = self.model.site("end_effector").id
        self.body = self.model.body("panda0_link7").id
        self.action_scale = env.action_scale.copy()  # Nm per action unit
        self.q_home = env.q_home.copy()
        self.k = 20 + 6 * env.n_obstacles
        if self.dynamic:
            self.kp = 100.0 if kp is None else float(kp)
            self.kd = 20.0 if kd is None else float(kd)
        else:
            self.kp = 600.0 if kp is None else float(kp)
            self.kd = 50.0 if kd is None else float(kd)
        self.k_null, self.d_null = (25.0, 10.0) if self.dynamic else (20.0, 5.0)
        self.jac = np.zeros((3, self.model.nv))
        self.jacdot = np.zeros((3, self.model.nv))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        mj, m, d = self._mj, self.model, self.data
        q, qd = obs[:7], obs[7:14]
        x, xd = obs[14:17], obs[17:20]
        k = self.k
        r, rd, rdd = obs[k : k + 3], obs[k + 3 : k + 6], obs[k + 6 : k + 9]
        d.qpos[:] = q
        d.qvel[:] = qd
        mj.mj_kinematics(m, d)
        mj.mj_comPos(m, d)
        mj.mj_jacSite(m, d, self.jac, None, self.site)
        J = self.jac
        JJt = J @ J.T + 1e-4 * np.eye(3)
        J_pinv = J.T @ np.linalg.inv(JJt)
        null = np.eye(7) - J_pinv @ J
        posture = self.k_null * (self.q_home - q) - self.d_null * qd
        e, ed = r - x, rd - xd
        if self.dynamic:
            mj.mj_comVel(m, d)
            mj.mj_jacDot(m, d, self.jacdot, None, d.site_xpos[self.site], self.body)
            acc = rdd + self.kp * e + self.kd * ed - self.jacdot @ qd
            d.qacc[:] = J_pinv @ acc + null @ posture
            mj.mj_forward(m, d)  # bias, passive (incl. gravcomp) of the nominal model
            d.qacc[:] = J_pinv @ acc + null @ posture
            mj.mj_inverse(m, d)
            tau = d.qfrc_inverse.copy()
        else:
            tau = J.T @ (self.kp * e + self.kd * ed) + null.T @ posture
        return tau / self.action_scale
