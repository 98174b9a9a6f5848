"""Policies for the bridge: ``policy(Observation) -> torque (7,)`` in Nm (numpy only).

``evaluate --agent`` builds its policies from a Gymnasium env's observation; the bridge has no
env, so it offers the subset that needs only the robot's state and model:

- ``"nominal"``: the simulation's obstacle-blind tracker (``NominalController`` with a
  dynamic model): inverse dynamics of the robot's model for the task-space acceleration
  ``x''_d = r'' + kp e + kd e' - J' q'`` of the end-effector point (0.21 m along link 7's z,
  the simulation's ``end_effector`` site; on the real arm 0.107 m flange + 0.1034 m hand),
  ``q''_d = J^+ x''_d + N (k_n (q_0 - q) - d_n q')``, ``tau = M q''_d + c`` (kp = 100 1/s^2,
  kd = 20 1/s, k_n = 25 1/s^2, d_n = 10 1/s), tracking the cyclic reference of paper Fig. 3
  (:class:`~afvsgp_gym.envs.scenario.CyclicReference`: 0.04 m along y for 2 s, then ramped
  to 0.28 m, period 4 s) around the end-effector's start;
- ``"hold"``: hold the start pose, ``tau = M (kp (q_0 - q) - kd q') + c`` (kp = 100 1/s^2,
  kd = 20 1/s);
- ``"zero"``: no torque (the arm floats on the robot's gravity compensation);

and the policies built to break the filter, as ``evaluate``'s
(:mod:`afvsgp_gym.agents.adversarial`), from the robot's state and the obstacle estimate:

- ``"ram"``: ``tau = J' k (p_o - p)``, a spring of ``k`` = 400 N/m without damping pulling
  the end-effector point at the nearest obstacle's reference point (it overshoots and rams);
- ``"swing1"`` to ``"swing7"``: full torque on one joint, its sign switching every second
  (the first sign from ``seed``), the other joints damped (``-q'`` per rad/s of the torque
  limit, clipped);
- ``"random"``: torques uniform within the limits, seeded (the rate limiter turns them into
  a random walk of 1 Nm steps).

The output is clipped to the torque limits.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from afvsgp_gym.envs.scenario import CyclicReference
from afvsgp_gym.robots.kinematics import END_EFFECTOR_OFFSET, DHChain, SphereKinematics
from afvsgp_gym.robots.libfranka import TAU_MAX
from afvsgp_gym.validation import check_choice, check_count

__all__ = ["ROBOT_AGENTS", "make_robot_policy"]

#: Agents of ``afvsgp-gym robot --agent``.
ROBOT_AGENTS = ("nominal", "hold", "zero", "ram", *(f"swing{j}" for j in range(1, 8)),
                "random")
#: s of the ``"nominal"`` tracker's warm-up (the small motion before the ramp); a moving
#: obstacle given without ``start_time`` starts then, as in the simulation.
WARMUP_SECONDS = 2.0


def cyclic_reference(center: np.ndarray, warmup: float = WARMUP_SECONDS) -> CyclicReference:
    """The simulation's reference (``FrankaObstacleEnv``'s, no switch) around ``center``."""
    ex, ey, ez = np.eye(3)
    return CyclicReference(center=np.asarray(center, dtype=np.float64).copy(), axis1=ey,
                           axis2=ez, amplitude=0.28, warmup_amplitude=0.04, period=4.0,
                           ramp_start=float(warmup), ramp_duration=1.0)


class TaskTracker:
    """The ``"nominal"`` policy (module docstring)."""

    def __init__(self, chain: DHChain, q0: np.ndarray, kp: float = 100.0, kd: float = 20.0,
                 k_null: float = 25.0, d_null: float = 10.0) -> None:
        self.q0 = np.asarray(q0, dtype=np.float64).copy()
        self.ee = SphereKinematics(chain, [7], [END_EFFECTOR_OFFSET])
        self.reference = cyclic_reference(self.ee.positions(self.q0)[0])
        self.kp, self.kd, self.k_null, self.d_null = kp, kd, k_null, d_null

    def __call__(self, obs) -> np.ndarray:
        q, dq = obs.q, obs.dq
        if obs.ee is None:
            p, v, jac, jdqd = (x[0] for x in self.ee(q, dq))
        else:  # the bridge's, computed with the spheres
            p, v, jac, jdqd = obs.ee
        J = jac
        r, rd, rdd = self.reference.state(obs.t)
        acc = rdd + self.kp * (r - p) + self.kd * (rd - v) - jdqd
        pinv = J.T @ np.linalg.inv(J @ J.T + 1e-4 * np.eye(3))
        null = np.eye(7) - pinv @ J
        posture = self.k_null * (self.q0 - q) - self.d_null * dq
        tau = obs.mass @ (pinv @ acc + null @ posture) + obs.coriolis
        return np.clip(tau, -TAU_MAX, TAU_MAX)


class PoseHold:
    """The ``"hold"`` policy (module docstring)."""

    def __init__(self, q0: np.ndarray, kp: float = 100.0, kd: float = 20.0) -> None:
        self.q0 = np.asarray(q0, dtype=np.float64).copy()
        self.kp, self.kd = kp, kd

    def __call__(self, obs) -> np.ndarray:
        acc = self.kp * (self.q0 - obs.q) - self.kd * obs.dq
        return np.clip(obs.mass @ acc + obs.coriolis, -TAU_MAX, TAU_MAX)


class TaskSpaceRam:
    """The ``"ram"`` policy (module docstring)."""

    def __init__(self, chain: DHChain, stiffness: float = 400.0) -> None:
        self.ee = SphereKinematics(chain, [7], [END_EFFECTOR_OFFSET])
        self.stiffness = float(stiffness)

    def __call__(self, obs) -> np.ndarray:
        if obs.ee is None:
            p, _, jac, _ = (x[0] for x in self.ee(obs.q, obs.dq))
        else:
            p, _, jac, _ = obs.ee
        centres = np.asarray(obs.obstacles.position, dtype=np.float64)
        if not len(centres):
            return np.zeros(7)
        target = centres[np.argmin(np.linalg.norm(centres - p, axis=1))]
        return np.clip(jac.T @ (self.stiffness * (target - p)), -TAU_MAX, TAU_MAX)


class JointSwing:
    """The ``"swing{joint}"`` policies (module docstring)."""

    def __init__(self, joint: int, seed: int = 0, half_period: float = 1.0,
                 damping: float = 1.0) -> None:
        self.joint = int(joint) - 1
        self.sign = -1.0 if seed % 2 else 1.0
        self.half_period, self.damping = float(half_period), float(damping)

    def __call__(self, obs) -> np.ndarray:
        tau = np.clip(-self.damping * np.asarray(obs.dq, dtype=np.float64), -1.0, 1.0) * TAU_MAX
        phase = int(obs.t // self.half_period) % 2
        tau[self.joint] = self.sign * (1.0 if phase == 0 else -1.0) * TAU_MAX[self.joint]
        return tau


class UniformTorque:
    """The ``"random"`` policy (module docstring)."""

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs) -> np.ndarray:
        return self.rng.uniform(-TAU_MAX, TAU_MAX)


def make_robot_policy(agent: str, chain: DHChain, q0: np.ndarray, seed: int = 0) -> Callable:
    """The policy ``agent`` (one of :data:`ROBOT_AGENTS`) for an arm of kinematics ``chain``
    starting at ``q0`` (``seed``: the swings' first sign, the random torques)."""
    check_choice("agent", agent, ROBOT_AGENTS)
    seed = check_count(seed, "seed", 0)
    if agent == "nominal":
        return TaskTracker(chain, q0)
    if agent == "hold":
        return PoseHold(q0)
    if agent == "ram":
        return TaskSpaceRam(chain)
    if agent.startswith("swing"):
        return JointSwing(int(agent[5:]), seed)
    if agent == "random":
        return UniformTorque(seed)
    return lambda obs: np.zeros(7)
