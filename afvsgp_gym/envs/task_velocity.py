"""Inner loop of the Franka reach task: an end-effector velocity command as joint torques.

The policy commands an end-effector velocity ``v_d = v_max u`` with ``u`` in [-1, 1]^3; at
the start of each control period the loop computes joint torques that are *affine in u*,

    tau = A(q, q') u + c(q, q'),

and holds them for the period (zero-order hold), so the barrier's second derivative keeps the
control-affine form of paper eq. 44 with respect to ``u``: if ``h'' = lf_tau + lg_tau tau``
for torques, then ``h'' = (lf_tau + lg_tau c) + (lg_tau A) u`` (:func:`compose_affine`).

The loop uses the arm's kinematics only (the translational Jacobian ``J`` of the
end-effector), never its inertia, payload or friction, which stay unknown to the filter:

- shoulder and elbow (joints 1-4): task-space damping towards the commanded velocity,
  ``tau_a = J_a' D (v_max u - J q') + N_a' (K_n (q_home - q)_a - D_n q'_a)``, with ``J_a``
  the Jacobian's columns of joints 1-4, ``N_a = I - J_a^+ J_a`` the null-space projector of
  the damped pseudo-inverse ``J_a^+ = J_a' (J_a J_a' + lambda I)^-1`` (posture of the elbow);
- wrist (joints 5-7): a joint PD hold of the ready pose, ``tau_w = K_w (q_home - q)_w -
  D_w q'_w``, independent of ``u``. The wrist joints' 12 Nm limits would saturate under
  ``J' F`` for task forces of a few tens of newtons; holding the wrist leaves the motion to
  the 87 Nm joints and keeps ``tau`` inside the limits in practice (tests/envs/test_reach.py
  counts saturated steps under random commands).

Residual gravity (payload, link mass errors) is not compensated: with ``u = 0`` the
end-effector sinks at roughly ``|F_g| / D`` (0.1 m/s for the default plant), which the
policy learns to offset and the filter learns as part of ``lf``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TaskVelocityLoop", "compose_affine"]


@dataclass(frozen=True)
class TaskVelocityLoop:
    """Gains of the end-effector velocity loop (see the module docstring).

    Attributes
    ----------
    max_speed : float
        ``v_max`` (m/s): end-effector velocity commanded by ``u`` = +-1 along one axis.
    damping : float
        ``D`` (N s/m): task-space damping towards the commanded velocity.
    posture_stiffness, posture_damping : float
        ``K_n`` (Nm/rad), ``D_n`` (Nm s/rad): null-space posture of joints 1-4.
    wrist_stiffness, wrist_damping : float
        ``K_w`` (Nm/rad), ``D_w`` (Nm s/rad): PD hold of joints 5-7.
    regularization : float
        ``lambda`` (m^2) of the damped pseudo-inverse.
    """

    max_speed: float = 0.3
    damping: float = 200.0
    posture_stiffness: float = 20.0
    posture_damping: float = 5.0
    wrist_stiffness: float = 15.0
    wrist_damping: float = 3.0
    regularization: float = 1e-4

    N_ARM = 4  # joints moved by the task-space term

    def affine_torque(
        self, jac: np.ndarray, q: np.ndarray, qd: np.ndarray, q_home: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(A (7, 3), c (7,))`` in Nm with ``tau = A u + c`` at the state ``(q, q')``.

        ``jac`` is the (3, 7) translational Jacobian of the end-effector (world frame)."""
        n = self.N_ARM
        ja = jac[:, :n]
        v = jac @ qd
        gram = ja @ ja.T + self.regularization * np.eye(3)
        pinv = np.linalg.solve(gram, ja).T  # J_a' (J_a J_a' + lambda I)^-1, gram symmetric
        null = np.eye(n) - pinv @ ja
        err = q_home - q
        A = np.zeros((7, 3))
        A[:n] = (self.damping * self.max_speed) * ja.T
        c = np.empty(7)
        c[:n] = -self.damping * (ja.T @ v) + null.T @ (
            self.posture_stiffness * err[:n] - self.posture_damping * qd[:n]
        )
        c[n:] = self.wrist_stiffness * err[n:] - self.wrist_damping * qd[n:]
        return A, c


def compose_affine(
    lf_tau: np.ndarray, lg_tau: np.ndarray, A: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Barrier terms w.r.t. ``u`` from those w.r.t. torques (per Nm) and ``tau = A u + c``:
    ``lf = lf_tau + lg_tau c``, ``lg = lg_tau A`` (K barriers: ``lf_tau`` (K,), ``lg_tau``
    (K, 7))."""
    return lf_tau + lg_tau @ c, lg_tau @ A
