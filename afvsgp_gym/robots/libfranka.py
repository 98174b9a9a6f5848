"""The part of libfranka's interface the bridge uses, as protocols, and the real robot behind it.

The shapes are pylibfranka 0.21's (the official bindings; ``pip install
'afvsgp-gym[robot]'``), which :mod:`afvsgp_gym.robots.simulated` reproduces for dry runs:

- ``Robot.start_torque_control() -> ActiveControl``; ``Robot.load_model() -> Model``;
  ``Robot.read_once() -> RobotState``; ``Robot.stop()``.
- ``ActiveControl.readOnce() -> (RobotState, Duration)`` blocks until the robot's next state
  (every 1 ms); ``ActiveControl.writeOnce(Torques)`` sends the torques for that period, on
  top of the robot's own gravity compensation; ``Torques(tau_J)`` with ``motion_finished``.
- ``RobotState``: ``q``, ``dq``, ``tau_J``, ``tau_J_d`` (7 each), ``O_T_EE``, ``F_T_EE``
  (4 x 4 poses, 16 column-major), ``robot_mode``, ``current_errors`` (truthy when some error
  flag is set), ``control_command_success_rate``, ``time`` (a ``Duration``, ``to_sec()``).
- ``Model.mass(state)`` (49, column-major, or (7, 7)), ``Model.coriolis(state)`` (7,),
  ``Model.gravity(state)`` (7,), ``Model.zero_jacobian(state)`` (42, column-major, or
  (6, 7)). In pylibfranka 0.21 neither ``Model`` nor ``RobotState`` has a constructor: a
  ``Model`` comes only from ``Robot.load_model()`` of a connected robot, so its
  ``zero_jacobian`` cannot be compared with the package's kinematics without one;
  :func:`check_kinematics` compares them (and the flange pose) on the robot, at the start.
- Errors: ``ControlException`` (the robot aborted the motion: a reflex, a limit, a torque
  discontinuity, too many lost commands) and ``NetworkException`` (the connection), both
  ``RuntimeError``.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from afvsgp_gym.envs.joint_limits import FRANKA_MAX_SPEED, FRANKA_MAX_TORQUE_RATE, JointLimits
from afvsgp_gym.robots.kinematics import FLANGE_OFFSET, DHChain, SphereKinematics

__all__ = ["CONTROL_PERIOD", "INSTALL_HINT", "KINEMATICS_TOLERANCE", "PANDA_LOWER",
           "PANDA_UPPER", "TAU_MAX", "ActiveControl", "Model", "MissingExtraError", "Robot",
           "RobotState", "as_matrix", "check_kinematics", "connect", "kinematics_error",
           "limit_rate", "panda_limits"]

#: libfranka's control period (s): one state and one command every millisecond.
CONTROL_PERIOD = 1e-3
#: Franka datasheet torque limits (Nm), joints 1-7.
TAU_MAX = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])
#: Franka Panda joint ranges (rad, datasheet), in the robot's own angles (FR3: its own).
PANDA_LOWER = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
PANDA_UPPER = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
#: Largest disagreement :func:`check_kinematics` accepts: flange position (m), flange
#: orientation (rad), end-effector Jacobian entry (m/rad).
KINEMATICS_TOLERANCE = (1e-3, 1e-2, 1e-3)
#: What to run when pylibfranka is missing.
INSTALL_HINT = "pip install 'afvsgp-gym[robot]'  (pylibfranka >= 0.21, Python 3.11 wheel)"


class MissingExtraError(ImportError):
    """pylibfranka is not installed (the optional extra ``robot``)."""


class RobotState(Protocol):
    q: Any
    dq: Any
    tau_J: Any
    current_errors: Any


class ActiveControl(Protocol):
    def readOnce(self) -> tuple[RobotState, Any]: ...  # noqa: N802 (libfranka's name)

    def writeOnce(self, command: Any) -> None: ...  # noqa: N802


class Model(Protocol):
    def mass(self, state: RobotState) -> Any: ...

    def coriolis(self, state: RobotState) -> Any: ...

    def gravity(self, state: RobotState) -> Any: ...


class Robot(Protocol):
    def start_torque_control(self) -> ActiveControl: ...

    def load_model(self) -> Model: ...

    def read_once(self) -> RobotState: ...

    def stop(self) -> None: ...


def as_matrix(values: Any, rows: int, cols: int) -> np.ndarray:
    """A libfranka matrix as float64 ``(rows, cols)``: a flat column-major array (the C++
    ``std::array``) or one already shaped (``reshape`` of the same shape is the identity)."""
    return np.asarray(values, dtype=np.float64).reshape(rows, cols, order="F")


def limit_rate(tau: np.ndarray, last: np.ndarray, max_rate: float = FRANKA_MAX_TORQUE_RATE,
               dt: float = CONTROL_PERIOD) -> np.ndarray:
    """libfranka's ``limitRate`` for torques: each joint's change from the last command
    ``last`` held to ``max_rate * dt`` (1000 Nm/s over 1 ms: 1 Nm per period)."""
    step = max_rate * dt
    return last + np.clip(tau - last, -step, step)


def panda_limits(range_margin: float = 0.1, speed_margin: float = 0.4) -> JointLimits:
    """The Panda's own joint ranges and speeds, with the barrier margins of the simulation."""
    return JointLimits(PANDA_LOWER, PANDA_UPPER, FRANKA_MAX_SPEED, range_margin, speed_margin)


def connect(host: str) -> tuple[Any, Any, Any]:
    """``(robot, model, torques)`` of the robot at ``host`` through pylibfranka:
    ``pylibfranka.Robot(host)``, its ``load_model()`` and the ``Torques`` command type.
    Raises :class:`MissingExtraError` (with :data:`INSTALL_HINT`) without pylibfranka."""
    try:
        import pylibfranka
    except ImportError:
        raise MissingExtraError(f"--host needs pylibfranka: {INSTALL_HINT}") from None
    robot = pylibfranka.Robot(str(host))
    return robot, robot.load_model(), pylibfranka.Torques


def kinematics_error(state: Any, model: Any, chain: DHChain) -> dict[str, float]:
    """How far ``chain`` is from the robot's own kinematics at ``state``: the flange
    position (m) and orientation (rad) against ``O_T_EE F_T_EE^-1`` (the state's 4 x 4
    column-major poses) and the end-effector point's translational Jacobian against
    ``Model.zero_jacobian(state)`` (its first three rows; the largest entry difference).
    On a connected robot this is the check that the package's DH table, joint offsets and
    frames are the robot's."""
    q = np.asarray(state.q, dtype=np.float64)
    o_t_ee = as_matrix(state.O_T_EE, 4, 4)
    f_t_ee = as_matrix(state.F_T_EE, 4, 4)
    robot_flange = o_t_ee @ np.linalg.inv(f_t_ee)
    mine = chain.flange(q)
    rel = robot_flange[:3, :3].T @ mine[:3, :3]
    skew = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
    angle = float(np.arctan2(0.5 * np.linalg.norm(skew), 0.5 * (np.trace(rel) - 1.0)))
    ee = f_t_ee[:3, 3] + np.array([0.0, 0.0, FLANGE_OFFSET])  # EE point in frame 7
    jac = SphereKinematics(chain, [7], [ee])(q, np.zeros(7))[2][0]
    robot_jac = as_matrix(model.zero_jacobian(state), 6, 7)[:3]
    return {"flange_position_m": float(np.linalg.norm(robot_flange[:3, 3] - mine[:3, 3])),
            "flange_rotation_rad": angle,
            "jacobian": float(np.abs(jac - robot_jac).max())}


def check_kinematics(state: Any, model: Any, chain: DHChain) -> dict[str, float]:
    """:func:`kinematics_error`, or ``RuntimeError`` when it exceeds
    :data:`KINEMATICS_TOLERANCE` (the bridge does not start on kinematics that are not the
    robot's)."""
    err = kinematics_error(state, model, chain)
    if any(v > tol for v, tol in zip(err.values(), KINEMATICS_TOLERANCE, strict=True)):
        raise RuntimeError(f"the kinematics {chain.name!r} are not the robot's: {err} "
                           f"(tolerances {KINEMATICS_TOLERANCE})")
    return err
