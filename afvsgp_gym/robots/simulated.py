"""A MuJoCo-backed stand-in for a Franka arm behind libfranka, for dry runs and tests.

:class:`SimulatedFranka` has the shapes of pylibfranka 0.21 that the bridge uses
(:mod:`afvsgp_gym.robots.libfranka`): ``start_torque_control()`` returns a control whose
``readOnce()`` gives ``(RobotState, Duration)`` and whose ``writeOnce(Torques)`` takes the
torques on top of the robot's gravity compensation; ``load_model()`` gives a ``Model`` with
``mass``, ``coriolis``, ``gravity`` and ``zero_jacobian`` of a :class:`RobotState`.

The plant is the gymnasium-robotics Panda of :mod:`afvsgp_gym.envs.franka_model` stepped by
MuJoCo every 1 ms (Euler, implicit joint damping), and it differs from the model it serves
as a real robot's does: the plant carries ``payload_mass`` at the flange (uncompensated),
link masses scaled by ``mass_scale``, joint ``damping`` and ``friction``; the served
``Model`` is the catalogue (unscaled links, no payload; the plant's rotor ``armature``),
whose gravity the plant compensates, as :class:`~afvsgp_gym.envs.franka.FrankaObstacleEnv`'s
``"perturbed"`` model. Obstacles rest or move in the workspace: spheres, boxes, capsules and
planes (:class:`~afvsgp_gym.envs.scenario.ObstacleSpec`, or the envs' ``obstacles=`` dicts),
MuJoCo geoms of their type named ``obstacle{i}`` that follow their motion;
:meth:`SimulatedFranka.obstacle_estimate` is the perception callback (their reference points'
true state, a centre or a plane's point, or a camera's estimate of the centres).
:meth:`SimulatedFranka.cost` checks the true state as the simulation does: a safety sphere
inside an obstacle (exact signed distance), an arm collision geom touching one
(``mj_geomDistance``), a joint at its limits.

Timing (``realtime=True``): ``readOnce`` blocks until the next 1 ms tick of the wall clock,
as the robot sends a state every millisecond. The command written since the last read drives
the plant over the next tick; when the bridge was late, the robot has gone on without it:
the missed ticks hold the previous command and count as lost (``control_command_success_rate``
over the last 100 ticks). With ``realtime=False`` every ``readOnce`` is one tick (tests).

The robot's own checks, as the real one's reflexes: a commanded torque step above 1000 Nm/s
(``controller_torque_discontinuity``), a joint at its range stop or above its datasheet
speed (``joint_position_limits_violation``, ``joint_velocity_violation``), an unstable
simulation (``instability_detected``) or a success rate below 80 %
(``communication_constraints_violation``) abort the motion: the ``readOnce`` of that tick
raises :class:`ControlException`, ``robot_mode`` becomes ``"Reflex"`` and ``current_errors`` names
the flags (``reflex=False`` turns the limit reflexes off, to test the bridge's own checks).
"""

from __future__ import annotations

import math
import os
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np

from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs.franka import self_contact_geom_pairs
from afvsgp_gym.envs.joint_limits import FRANKA_MAX_SPEED, FRANKA_MAX_TORQUE_RATE, JointLimits
from afvsgp_gym.envs.primitives import Plane, pair_barriers, stack_shapes
from afvsgp_gym.envs.safety_spheres import PANDA_ARM_SPHERES, SafetySphere, sphere_arrays
from afvsgp_gym.envs.scenario import OBSTACLE_TYPES, ObstacleSpec, parse_obstacles
from afvsgp_gym.robots.kinematics import (
    END_EFFECTOR_OFFSET,
    FLANGE_OFFSET,
    GYMNASIUM_PANDA,
    DHChain,
    SphereKinematics,
)
from afvsgp_gym.robots.libfranka import CONTROL_PERIOD, TAU_MAX
from afvsgp_gym.robots.policies import WARMUP_SECONDS
from afvsgp_gym.robots.terms import ObstacleEstimate
from afvsgp_gym.validation import check_real

__all__ = ["ControlException", "CostLog", "Duration", "Errors", "NetworkException",
           "RobotState", "SimulatedFranka", "Torques", "dynamic_obstacle"]

_BAD_WARNINGS = np.array([int(mujoco.mjtWarning.mjWARN_BADQACC),
                          int(mujoco.mjtWarning.mjWARN_BADQPOS),
                          int(mujoco.mjtWarning.mjWARN_BADQVEL)])

#: Below this share of commands received over the last 100 ticks the stand-in aborts.
MIN_SUCCESS_RATE = 0.8
#: At real-time priority ``readOnce`` sleeps until this long (s) before the tick, then
#: spins (spinning the whole wait there meets the kernel's real-time throttling, 50 ms in
#: every second); at normal priority it spins the whole wait (a sleeping process on a busy
#: machine gets the CPU back milliseconds late).
SPIN = 1e-4


class ControlException(RuntimeError):
    """The robot aborted the motion (pylibfranka's ``ControlException``)."""


class NetworkException(RuntimeError):
    """The connection failed (pylibfranka's ``NetworkException``)."""


@dataclass(frozen=True)
class Duration:
    """pylibfranka's ``Duration``."""

    seconds: float

    def to_sec(self) -> float:
        return self.seconds


@dataclass
class Errors:
    """The error flags the stand-in raises (pylibfranka's ``Errors``: truthy when any is set,
    ``str`` lists them)."""

    flags: tuple[str, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.flags)

    def __str__(self) -> str:
        return ", ".join(self.flags)

    def __getattr__(self, name: str) -> bool:
        if name.startswith("_"):
            raise AttributeError(name)
        return name in self.flags


@dataclass
class RobotState:
    """The fields of pylibfranka's ``RobotState`` the bridge reads."""

    q: np.ndarray
    dq: np.ndarray
    tau_J: np.ndarray  # noqa: N815 (libfranka's names)
    tau_J_d: np.ndarray  # noqa: N815
    time: Duration
    O_T_EE: list = field(default_factory=list)  # noqa: N815 (4 x 4, column-major)
    F_T_EE: list = field(default_factory=list)  # noqa: N815
    robot_mode: str = "Move"
    current_errors: Errors = field(default_factory=Errors)
    control_command_success_rate: float = 1.0


class Torques:
    """pylibfranka's ``Torques(tau_J)`` command, with ``motion_finished``."""

    def __init__(self, tau_J: Sequence[float]) -> None:  # noqa: N803
        self.tau_J = [float(x) for x in tau_J]
        if len(self.tau_J) != 7:
            raise ValueError(f"tau_J must hold 7 torques. Got: {len(self.tau_J)}")
        self.motion_finished = False


def dynamic_obstacle(center: np.ndarray, start_time: float = 2.0,
                     speed: float = 0.15, radius: float = 0.05) -> ObstacleSpec:
    """The simulation's ``"dynamic"`` scenario's sphere for a reference centre ``center``: at
    rest 0.5 m away in +x, it moves onto the reference's path at ``start_time`` (s), 0.15 m
    along y and 0.07 m below the centre, with peak speed ``speed`` (m/s), and stays."""
    c = np.asarray(center, dtype=np.float64)
    end = c + np.array([0.0, 0.15, -0.07])
    return ObstacleSpec(end, float(radius), end + np.array([0.5, 0.0, 0.0]), float(start_time),
                        float(speed))


def _realtime_scheduled() -> bool:
    """True when this process runs at a real-time priority (SCHED_FIFO or SCHED_RR)."""
    try:
        return os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR)
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return False


def _inertia(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """``M`` (nv, nv) after ``mj_fwdPosition``, column by column (any MuJoCo version)."""
    out = np.empty((model.nv, model.nv))
    for i, e in enumerate(np.eye(model.nv)):
        mujoco.mj_mulM(model, data, out[i], e)
    return out


class SimulatedModel:
    """The catalogue model behind ``load_model()``: libfranka's ``Model`` calls, computed by
    MuJoCo for the state's ``q`` and ``dq``."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self._model = model
        self._data = mujoco.MjData(model)
        self._site = model.site(fm.EE_SITE).id
        self._key: tuple | None = None

    def _at(self, state: RobotState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = np.asarray(state.q, dtype=np.float64)
        dq = np.asarray(state.dq, dtype=np.float64)
        key = (q.tobytes(), dq.tobytes())
        if key != self._key:
            m, d = self._model, self._data
            d.qpos[:], d.qvel[:] = q, 0.0
            mujoco.mj_fwdPosition(m, d)
            mujoco.mj_comVel(m, d)
            rest = np.empty(m.nv)
            mujoco.mj_rne(m, d, 0, rest)  # gravity: the bias at rest
            d.qvel[:] = dq
            mujoco.mj_comVel(m, d)
            bias = np.empty(m.nv)
            mujoco.mj_rne(m, d, 0, bias)
            self._values = (_inertia(m, d), bias - rest, rest)
            self._key = key
        return self._values

    def mass(self, state: RobotState) -> list[float]:
        """``M(q)`` (kg m^2), 49 values in column-major order."""
        return self._at(state)[0].ravel(order="F").tolist()

    def coriolis(self, state: RobotState) -> list[float]:
        """``C(q, q') q'`` (Nm), 7 values."""
        return self._at(state)[1].tolist()

    def gravity(self, state: RobotState) -> list[float]:
        """``g(q)`` (Nm), 7 values (the robot compensates it)."""
        return self._at(state)[2].tolist()

    def zero_jacobian(self, state: RobotState) -> list[float]:
        """The end-effector site's Jacobian in the base frame, ``[J_v; J_w]`` (6, 7),
        42 values in column-major order."""
        m, d = self._model, self._data
        d.qpos[:] = np.asarray(state.q, dtype=np.float64)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        jac = np.zeros((6, m.nv))
        mujoco.mj_jacSite(m, d, jac[:3], jac[3:], self._site)
        self._key = None
        return jac.ravel(order="F").tolist()


class SimulatedControl:
    """The active torque control of a :class:`SimulatedFranka` (``readOnce``,
    ``writeOnce``)."""

    def __init__(self, robot: SimulatedFranka) -> None:
        self._robot = robot
        self._written: np.ndarray | None = None
        self._first = True
        self.finished = False

    def readOnce(self) -> tuple[RobotState, Duration]:  # noqa: N802 (libfranka's name)
        """Wait for the next tick (wall clock with ``realtime``), advance the plant by every
        tick since the last read and return its state and the time that passed (the first
        read: the state at the start, ``Duration(0)``)."""
        robot = self._robot
        if self.finished:
            raise ControlException("libfranka: the motion has finished")
        if self._first:  # the state the motion starts from: no command is due yet
            self._first = False
            robot._raise_pending()
            return robot.read_once(), Duration(0.0)
        ticks = robot._wait_for_tick()
        command, self._written = self._written, None
        for i in range(ticks):
            robot._advance(command if i == 0 else None)
        robot._raise_pending()
        return robot.read_once(), Duration(ticks * CONTROL_PERIOD)

    def writeOnce(self, command: Torques) -> None:  # noqa: N802
        """The torques (Nm, on top of the gravity compensation) for the coming tick."""
        tau = np.asarray(command.tau_J, dtype=np.float64)
        if tau.shape != (7,) or not np.isfinite(tau).all():
            raise ValueError(f"Commanded torque must be 7 finite values. Got: {command.tau_J}")
        self._written = tau
        if getattr(command, "motion_finished", False):
            self._robot._advance(tau)
            self.finished = True
            self._robot.mode = "Idle"


class CostLog:
    """The stand-in's true-state cost check, kept out of the 1 kHz loop
    (:meth:`SimulatedFranka.cost_log`).

    :meth:`record`, called where the bridge would call ``cost()`` (after each write), copies
    the plant's joint state and tick (a few microseconds); :meth:`count`, after the run,
    puts each recorded state on a scratch copy of the plant and counts those
    :meth:`SimulatedFranka.cost` finds: the same answers as the check in the loop (the
    obstacles' places are functions of time), without its 0.1-0.3 ms per tick (the contact
    and self-contact tests) on the loop, which a real robot does not run either.
    ``min_clearance`` is the smallest true clearance (m) of the states counted."""

    def __init__(self, robot: SimulatedFranka):
        self.robot = robot
        self._ticks: list[int] = []
        self._qpos: list[np.ndarray] = []
        self._qvel: list[np.ndarray] = []
        self.min_clearance = math.inf

    def __len__(self) -> int:
        return len(self._ticks)

    def record(self) -> None:
        """Keep the plant's state now."""
        d = self.robot.data
        self._ticks.append(self.robot.ticks)
        self._qpos.append(d.qpos.copy())
        self._qvel.append(d.qvel.copy())

    def count(self) -> int:
        """How many recorded states have cost (and ``min_clearance`` over them)."""
        robot = self.robot
        saved = robot.data, robot.ticks
        robot.data = scratch = mujoco.MjData(robot.model)
        n = 0
        try:
            for ticks, qpos, qvel in zip(self._ticks, self._qpos, self._qvel, strict=True):
                robot.ticks = ticks
                scratch.qpos[:] = qpos
                scratch.qvel[:] = qvel
                robot._place_obstacles()
                mujoco.mj_kinematics(robot.model, scratch)
                n += robot.cost()
                self.min_clearance = min(self.min_clearance, float(robot.clearance().min()))
        finally:
            robot.data, robot.ticks = saved
        return n


class SimulatedFranka:
    """A Franka arm with libfranka's shapes, simulated by MuJoCo at 1 kHz (module docstring).

    Parameters
    ----------
    obstacles : sequence of ObstacleSpec or dict, or None
        The obstacles in the workspace: specs of any type (:meth:`ObstacleSpec.of_shape
        <afvsgp_gym.envs.scenario.ObstacleSpec.of_shape>`) or the envs' ``obstacles=``
        dicts (``"type"`` ``"sphere"``, ``"box"``, ``"capsule"``, ``"plane"``; a moving one's
        ``start_time`` defaults to the tracker's warm-up, 2 s); None: :func:`dynamic_obstacle`
        for the reference centre (the end-effector at ``q0``).
    payload_mass, mass_scale, damping, friction, armature
        The true plant (as :class:`~afvsgp_gym.envs.franka.FrankaObstacleEnv`'s; one
        ``mass_scale`` for every link).
    q0 : array_like of shape (7,)
        Starting joint angles (rad), at rest; the ready pose by default.
    realtime : bool
        Pace ``readOnce`` by the wall clock (1 kHz); False: one tick per call.
    reflex : bool
        Abort on the joint range and speed limits, as the robot does.
    obstacle_noise : float
        0 (default): :meth:`obstacle_estimate` is the obstacles' true state. > 0 (m): a camera
        samples each centre (a box's, a capsule's) at ``obstacle_rate`` Hz with this noise per
        axis (seeded by ``seed``) and :meth:`obstacle_estimate` is the
        :class:`~afvsgp_gym.cbf.estimation.ObstacleEstimator`'s (constant velocity, process
        noise 1 m s^-1.5) at the control time, with its covariance. Planes (a table, a wall:
        the cell's, measured once) are given exactly, with covariance 0.
    obstacle_rate : float
        Hz, the camera's sample rate.
    seed : int
        The camera noise's.
    """

    #: The kinematics of this arm's angles (the gymnasium-robotics Panda).
    kinematics: DHChain = GYMNASIUM_PANDA
    #: The safety spheres, in the link frames.
    spheres: tuple[SafetySphere, ...] = PANDA_ARM_SPHERES

    def __init__(self, obstacles: Sequence[ObstacleSpec] | None = None, *,
                 payload_mass: float = 1.0, mass_scale: float = 1.0, damping: float = 1.0,
                 friction: float = 0.0, armature: float = 0.1,
                 q0=None, realtime: bool = True, reflex: bool = True,
                 obstacle_noise: float = 0.0, obstacle_rate: float = 30.0,
                 seed: int = 0) -> None:
        payload_mass = check_real(payload_mass, "payload_mass", low=0.0)
        mass_scale = check_real(mass_scale, "mass_scale", low=0.0, low_open=True)
        damping = check_real(damping, "damping", low=0.0)
        friction = check_real(friction, "friction", low=0.0)
        armature = check_real(armature, "armature", low=0.0)
        self.obstacle_noise = check_real(obstacle_noise, "obstacle_noise", low=0.0)
        self.obstacle_rate = check_real(obstacle_rate, "obstacle_rate", low=0.0, low_open=True)
        q0 = fm.Q_HOME.copy() if q0 is None else np.asarray(q0, dtype=np.float64)
        if q0.shape != (7,) or not np.isfinite(q0).all():
            raise ValueError(f"q0 must be 7 finite joint angles. Got: {q0!r}")
        self.realtime, self.reflex = bool(realtime), bool(reflex)
        #: The end-effector site at ``q0`` (m): the centre of the default reference.
        self.reference_center = SphereKinematics(self.kinematics, [7], [END_EFFECTOR_OFFSET]
                                                 ).positions(q0)[0]
        if obstacles is None:
            obstacles = [dynamic_obstacle(self.reference_center)]
        #: The obstacles (ObstacleSpec), in the order of the barrier pairs.
        self.obstacles = tuple(parse_obstacles(obstacles, 3, WARMUP_SECONDS, OBSTACLE_TYPES))
        scene = fm.SceneOptions(tuple(o.radius for o in self.obstacles), 0.05, CONTROL_PERIOD,
                                tuple(fm.obstacle_geom(o) for o in self.obstacles))
        plant = fm.PlantParameters(mass_scale=np.full(9, mass_scale), payload_mass=payload_mass,
                                   damping=np.full(7, damping), frictionloss=np.full(7, friction),
                                   armature=np.full(7, armature))
        self.model = fm.build_model(plant, scene)
        self.model.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
        self.data = mujoco.MjData(self.model)
        self._catalogue = fm.build_model(fm.PlantParameters(armature=plant.armature), scene)
        m = self.model
        #: The joint ranges of this arm (the model's) and the datasheet speeds.
        self.joint_limits = JointLimits(m.jnt_range[:7, 0], m.jnt_range[:7, 1],
                                        FRANKA_MAX_SPEED, 0.1, 0.4)
        bodies, self._offsets, self.sphere_radii = sphere_arrays(self.spheres)
        self._sphere_bodies = np.array([m.body(b).id for b in bodies])
        self._obstacle_radii = np.array([o.radius for o in self.obstacles])
        self._setup_obstacle_checks()
        self._site = m.site(fm.EE_SITE).id
        f_t_ee = np.eye(4)  # the site in the flange frame (link 7 moved 0.107 m along z)
        quat = m.site_quat[self._site]
        mat = np.empty(9)
        mujoco.mju_quat2Mat(mat, quat)
        f_t_ee[:3, :3] = mat.reshape(3, 3)
        f_t_ee[:3, 3] = m.site_pos[self._site] - np.array([0.0, 0.0, FLANGE_OFFSET])
        self._f_t_ee = f_t_ee.ravel(order="F").tolist()
        self.ticks = 0
        self.data.qpos[:] = q0
        self.data.qvel[:] = 0.0
        self._place_obstacles()
        mujoco.mj_forward(m, self.data)
        self.mode = "Idle"
        self._errors: tuple[str, ...] = ()
        self._pending_error: str | None = None
        self._applied = np.zeros(7)  # the torque acting now (the last command received)
        self._received: deque[bool] = deque(maxlen=100)
        self._t0: float | None = None
        self.lost_commands = 0
        self._estimator = None
        #: The obstacles the camera senses (not the planes).
        self._sensed = [i for i, o in enumerate(self.obstacles) if not isinstance(o.shape, Plane)]
        if self.obstacle_noise > 0 and self._sensed:
            from afvsgp_gym.cbf.estimation import ObstacleEstimator

            self._estimator = ObstacleEstimator(len(self._sensed), self.obstacle_noise)
            self._camera_rng = np.random.default_rng(int(seed))
            self._next_sample = 0

    # ------------------------------------------------------------------ libfranka's calls
    def start_torque_control(self) -> SimulatedControl:
        """Torque control from now: the clock starts at the next tick."""
        if self._pending_error is not None or self.mode == "Reflex":
            raise ControlException(f"libfranka: cannot start: robot in reflex mode "
                                   f"[{', '.join(self._errors)}]")
        self.mode = "Move"
        self._sleep = _realtime_scheduled()
        self._t0 = time.perf_counter()
        self._tick0 = self.ticks
        return SimulatedControl(self)

    def load_model(self) -> SimulatedModel:
        return SimulatedModel(self._catalogue)

    def read_once(self) -> RobotState:
        d = self.data
        rate = (sum(self._received) / len(self._received)) if self._received else 1.0
        ee = np.eye(4)  # the end-effector site's frame (kinematics fresh after each tick)
        ee[:3, :3] = d.site_xmat[self._site].reshape(3, 3)
        ee[:3, 3] = d.site_xpos[self._site]
        return RobotState(q=d.qpos[:7].copy(), dq=d.qvel[:7].copy(),
                          tau_J=self._applied.copy(), tau_J_d=self._applied.copy(),
                          time=Duration(self.ticks * CONTROL_PERIOD),
                          O_T_EE=ee.ravel(order="F").tolist(), F_T_EE=self._f_t_ee,
                          robot_mode=self.mode, current_errors=Errors(self._errors),
                          control_command_success_rate=rate)

    def stop(self) -> None:
        self.mode = "Idle"

    def automatic_error_recovery(self) -> None:
        self._errors, self._pending_error = (), None
        self.mode = "Idle"

    # ------------------------------------------------------------------ the simulation
    @property
    def time(self) -> float:
        """Simulated time (s)."""
        return self.ticks * CONTROL_PERIOD

    def obstacle_estimate(self, t: float | None = None) -> ObstacleEstimate:
        """The perception callback at ``t`` (s; default: now): the obstacles' true state, or
        with ``obstacle_noise`` the Kalman estimate from the camera's samples up to ``t``."""
        t = self.time if t is None else float(t)
        if self._estimator is None:
            return self.true_obstacles(t)
        est, sensed = self._estimator, self._sensed
        every = len(sensed) == len(self.obstacles)
        while self._next_sample / self.obstacle_rate <= t + 1e-12:  # the samples taken by t
            ts = self._next_sample / self.obstacle_rate
            true = self.true_obstacles(ts).position
            true = true if every else true[sensed]
            est.update(true + self._camera_rng.normal(0.0, self.obstacle_noise, true.shape), ts)
            self._next_sample += 1
        if every:
            return ObstacleEstimate(*est.predict(t))
        exact = self.true_obstacles(t)  # the planes': exact, covariance 0
        pos, vel, acc = exact.position, exact.velocity, exact.acceleration
        cov = np.zeros((len(self.obstacles), 3, 3))
        pos[sensed], vel[sensed], acc[sensed], cov[sensed] = est.predict(t)
        return ObstacleEstimate(pos, vel, acc, cov)

    def true_obstacles(self, t: float | None = None) -> ObstacleEstimate:
        """The obstacles' true state at ``t`` (s; default: now)."""
        t = self.time if t is None else float(t)
        states = [o.state(t) for o in self.obstacles]
        return ObstacleEstimate(np.array([s[0] for s in states]),
                                np.array([s[1] for s in states]),
                                np.array([s[2] for s in states]))

    def set_state(self, q, dq) -> None:
        """Put the plant at ``q``, ``dq`` (tests)."""
        self.data.qpos[:] = q
        self.data.qvel[:] = dq
        self._place_obstacles()
        mujoco.mj_forward(self.model, self.data)

    def clearance(self) -> np.ndarray:
        """``h`` (O S,) of every (sphere, obstacle) pair at the true state, from MuJoCo's
        body frames: the exact signed distance of each obstacle's primitive
        (:func:`~afvsgp_gym.envs.primitives.pair_barriers`) less the sphere's radius."""
        d = self.data  # (its frames are the state's: _advance and set_state refresh them)
        b = self._sphere_bodies
        p = np.einsum("sij,sj->si", d.xmat[b].reshape(-1, 3, 3), self._offsets) + d.xpos[b]
        pos = self.true_obstacles().position
        if self._shapes is None:  # spheres only: the sphere formula, as before
            dist = np.linalg.norm(p[None, :, :] - pos[:, None, :], axis=2)
            return (dist - self._obstacle_radii[:, None] - self.sphere_radii[None, :]).ravel()
        rel = (p[None, :, :] - pos[:, None, :]).reshape(-1, 3)
        return pair_barriers(self._shapes, rel, np.zeros_like(rel), self._pair_sphere_radii)[0]

    def contact(self) -> bool:
        """True when an arm collision geom (links 1-7, hand, fingers) touches an obstacle
        geom at the true state (``mj_geomDistance`` < 0), as the simulation's contact check:
        only the geoms whose bounding sphere reaches the obstacle's (a plane's half-space)
        are asked."""
        m, d = self.model, self.data
        pos = d.geom_xpos[self._arm_geoms]
        for k, g_obs in enumerate(self._obstacle_geoms):
            ob = self.obstacles[k]
            diff = pos - ob.state(self.time)[0]
            if isinstance(ob.shape, Plane):  # the geoms' bounding spheres reaching the plane
                near = diff @ ob.shape.normal < self._arm_rbound
            else:
                near = np.einsum("ij,ij->i", diff, diff) < self._reach2[k]
            for g in self._arm_geoms[near]:
                if mujoco.mj_geomDistance(m, d, int(g), int(g_obs), 0.01, None) < 0:
                    return True
        return False

    def self_contact(self) -> bool:
        """True when two of the robot's collision geoms on non-adjacent links touch (the
        simulation's ``info["self_contact"]``)."""
        return self._self_contact_pairs.touching(self.model, self.data)

    def cost(self) -> bool:
        """True when the true state has a sphere inside an obstacle, an arm geom touching
        one (:meth:`contact`), a joint at its range stop or above its datasheet speed, or
        the arm touching itself or its base (:meth:`self_contact`), as the simulation's
        cost."""
        d = self.data
        return bool(self.clearance().min() < 0.0
                    or self.joint_limits.violation(d.qpos[:7], d.qvel[:7])
                    or self.contact() or self.self_contact())

    def cost_log(self) -> CostLog:
        """A :class:`CostLog` of this plant: :meth:`cost` after the run instead of in it."""
        return CostLog(self)

    def _setup_obstacle_checks(self) -> None:
        """The obstacle geoms and mocap bodies, the arm's collision geoms and their reach
        (the contact check), and the primitives' stack for a scene that is not spheres only
        (:meth:`clearance`)."""
        m = self.model
        n_o = len(self.obstacles)
        self._obstacle_geoms = np.array([m.geom(f"obstacle{i}").id for i in range(n_o)])
        self._obstacle_mocap = np.array([m.body_mocapid[m.body(f"obstacle{i}").id]
                                         for i in range(n_o)])
        self._arm_geoms = fm.arm_collision_geoms(m)
        self._self_contact_pairs = self_contact_geom_pairs(m)
        self._arm_rbound = m.geom_rbound[self._arm_geoms].copy()
        reach = self._arm_rbound[None, :] + self._obstacle_radii[:, None]
        self._reach2 = reach * reach
        self._shapes = None
        if any(o.shape is not None for o in self.obstacles):
            self._shapes = stack_shapes([o.primitive for o in self.obstacles],
                                        len(self.sphere_radii))
            self._pair_sphere_radii = np.tile(self.sphere_radii, n_o)

    def _place_obstacles(self) -> None:
        """The obstacle bodies (mocap) at the obstacles' places now (their geoms follow at
        the next kinematics; they do not enter the arm's dynamics: contacts are off)."""
        t = self.time
        for k, ob in zip(self._obstacle_mocap, self.obstacles, strict=True):
            self.data.mocap_pos[k] = ob.state(t)[0]

    def _raise_pending(self) -> None:
        if self._pending_error is not None:
            error, self._pending_error = self._pending_error, None
            raise ControlException(f"libfranka: Move command aborted: motion aborted by "
                                   f"reflex! [{error}]")

    def _wait_for_tick(self) -> int:
        """Block until the next tick; the ticks passed since the last read (>= 1)."""
        self._raise_pending()
        if self._t0 is None:
            raise ControlException("libfranka: no active control")
        if not self.realtime:
            return 1
        due = self._t0 + (self.ticks + 1 - self._tick0) * CONTROL_PERIOD
        now = time.perf_counter()
        if self._sleep and due - now > SPIN:  # sleep, then spin the last SPIN s
            time.sleep(due - now - SPIN)
        while now < due:
            now = time.perf_counter()
        return max(1, int((now - self._t0) / CONTROL_PERIOD) - (self.ticks - self._tick0))

    def _advance(self, command: np.ndarray | None) -> None:
        """One 1 ms tick with ``command`` (None: lost, the previous one holds), then the
        robot's own checks."""
        received = command is not None
        self._received.append(received)
        if not received:
            self.lost_commands += 1
            command = self._applied
        flags = []
        if np.any(np.abs(command - self._applied) > FRANKA_MAX_TORQUE_RATE * CONTROL_PERIOD
                  * (1.0 + 1e-9)):
            flags.append("controller_torque_discontinuity")
        self._applied = command.copy()
        m, d = self.model, self.data
        d.ctrl[:] = np.clip(command / TAU_MAX, -1.0, 1.0)
        warnings = int(d.warning.number[_BAD_WARNINGS].sum())
        mujoco.mj_step(m, d)  # (MuJoCo resets a state that goes non-finite, and warns)
        self.ticks += 1
        self._place_obstacles()
        mujoco.mj_kinematics(m, d)  # the frames of the new state (mj_step leaves the old)
        q, dq = d.qpos[:7], d.qvel[:7]
        if int(d.warning.number[_BAD_WARNINGS].sum()) > warnings or not (
                math.isfinite(float(q.sum())) and math.isfinite(float(dq.sum()))):
            flags.append("instability_detected")
        elif self.reflex:
            lim = self.joint_limits
            if np.any(q <= lim.lower) or np.any(q >= lim.upper):
                flags.append("joint_position_limits_violation")
            if np.any(np.abs(dq) > lim.max_speed):
                flags.append("joint_velocity_violation")
        if len(self._received) == self._received.maxlen and \
                sum(self._received) < MIN_SUCCESS_RATE * len(self._received):
            flags.append("communication_constraints_violation")
        if flags and self._pending_error is None:
            self._errors = tuple(flags)
            self._pending_error = ", ".join(flags)
            self.mode = "Reflex"
