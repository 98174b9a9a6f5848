"""One run of the bridge, assembled: on the MuJoCo stand-in (:func:`run_simulated`) or on a
robot through pylibfranka (:func:`run_robot`); what ``afvsgp-gym robot`` calls."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from afvsgp_gym.envs.joint_limits import JointLimits
from afvsgp_gym.envs.safety_spheres import PANDA_ARM_SPHERES, SafetySphere, sphere_arrays
from afvsgp_gym.envs.scenario import OBSTACLE_TYPES, ObstacleSpec, parse_obstacles
from afvsgp_gym.robots.bridge import Bridge, BridgeReport
from afvsgp_gym.robots.kinematics import FRANKA_PANDA, DHChain, SphereKinematics
from afvsgp_gym.robots.libfranka import TAU_MAX, check_kinematics, connect, panda_limits
from afvsgp_gym.robots.policies import WARMUP_SECONDS, make_robot_policy
from afvsgp_gym.robots.terms import BarrierModel, ObstacleEstimate, panda_self_collision_pairs

__all__ = ["build_bridge", "make_controller", "obstacle_specs", "realtime_priority", "run_robot",
           "run_simulated", "scripted_obstacles", "static_obstacles"]


@contextlib.contextmanager
def realtime_priority(priority: int | None, enforce: bool = False) -> Iterator[str]:
    """Run the block at SCHED_FIFO ``priority`` (1-99), restoring the scheduler after; yields
    what the process ran at (``"SCHED_OTHER"`` for None or 0, or when the system refuses: the
    reason). With ``enforce`` a refusal raises ``RuntimeError`` instead, as libfranka's
    ``RealtimeConfig.kEnforce`` (its default) refuses to start a control loop without a
    real-time priority."""
    if not priority:
        yield "SCHED_OTHER"
        return
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))
    except (AttributeError, OSError) as exc:
        if enforce:
            raise RuntimeError(
                f"SCHED_FIFO {priority} refused ({exc}): a real-time priority needs root or "
                "an rtprio limit (/etc/security/limits.conf, docs/robot.md); --rt-priority 0 "
                "runs at normal priority, which libfranka's default refuses too") from None
        yield f"SCHED_OTHER (SCHED_FIFO {priority} refused: {exc})"
        return
    try:
        yield f"SCHED_FIFO {int(priority)}"
    finally:
        os.sched_setscheduler(0, before[0], before[1])


def make_controller(barriers: BarrierModel, learner: str = "none", **filter_kwargs: Any):
    """A :class:`~afvsgp_gym.cbf.SafetyController` for ``barriers`` with torques in Nm
    (bounds +-``TAU_MAX``), the simulation's suggested options under ``filter_kwargs``; a
    learner that projects the pairs onto shared learners (``"afvsgp-shared"``) gets
    ``barriers.shared_layout``."""
    from afvsgp_gym.cbf import SafetyController
    from afvsgp_gym.cbf.learners import REGISTRY, check_learner_name

    options = {**barriers.filter_defaults, **filter_kwargs}
    if learner == "none":  # no band to correct
        for name in ("calibration", "calibration_step", "calibration_gate"):
            options.pop(name, None)
    projected = REGISTRY[check_learner_name(learner)].projected
    layout = barriers.shared_layout if projected else barriers.layout
    ctrl = SafetyController(-TAU_MAX, TAU_MAX, barriers.n_barriers, learner,
                            layout=layout, relative_degree=2, **options)
    if ctrl.uses_true_terms:
        raise ValueError(f"learner {learner!r} needs the true terms, which a robot does not "
                         "have; use a learner or 'none'")
    ctrl.prepare_programs()  # every program size: no solver is built inside the 1 kHz loop
    return ctrl


def build_bridge(robot: Any, model: Any, torques: Callable, *, chain: DHChain,
                 obstacle_radii: Sequence[float], obstacles: Callable[[float], ObstacleEstimate],
                 limits: JointLimits, agent: str = "nominal", learner: str = "none",
                 spheres: Sequence[SafetySphere] = PANDA_ARM_SPHERES, budget: float = 0.9e-3,
                 cost: Callable[[], bool] | Any | None = None, torque_error=0.0,
                 filter_kwargs: dict | None = None,
                 obstacle_shapes: Sequence | None = None,
                 self_collision: bool | None = None, background_fit: bool = True,
                 seed: int = 0) -> Bridge:
    """The :class:`~afvsgp_gym.robots.bridge.Bridge` of one robot: its kinematics ``chain``,
    safety ``spheres``, joint ``limits``, the obstacles' radii (and ``obstacle_shapes``:
    :class:`~afvsgp_gym.robots.terms.BarrierModel`'s ``shapes``, None: spheres) and
    perception callback (``self_collision``: the self-collision barriers of
    :func:`~afvsgp_gym.robots.terms.panda_self_collision_pairs` too, chosen for the Panda's
    arm spheres; None, the default: on with those spheres, as in the simulation, off with
    others; docs/robot.md has what they prevent and cost), the policy ``agent``
    (:data:`~afvsgp_gym.robots.policies.ROBOT_AGENTS`; ``seed`` for those that draw) from the
    robot's current pose and a
    filter with ``learner`` (``filter_kwargs``: its options; their ``backend`` selects the
    kinematics' and the terms' too; ``background_fit``: the learners' warm-up fit in a
    process of its own, :class:`~afvsgp_gym.robots.bridge.Bridge`'s). ``chain`` is first
    checked against the robot's own flange pose and Jacobian
    (:func:`~afvsgp_gym.robots.libfranka.check_kinematics`; ``RuntimeError`` when they
    disagree)."""
    state = robot.read_once()
    checked = check_kinematics(state, model, chain)  # RuntimeError: not the robot's
    backend = (filter_kwargs or {}).get("backend", "auto")  # the one switch, as the filter's
    kin = SphereKinematics.from_spheres(chain, spheres, backend=backend)
    if self_collision is None:
        self_collision = tuple(spheres) == PANDA_ARM_SPHERES
    if self_collision and tuple(spheres) != PANDA_ARM_SPHERES:
        raise ValueError("self_collision=True needs the Panda's arm spheres (its pairs are "
                         "chosen for them). Got: other spheres")
    pairs = panda_self_collision_pairs() if self_collision else None
    barriers = BarrierModel(kin, sphere_arrays(spheres)[2], obstacle_radii, limits,
                            torque_error=torque_error, shapes=obstacle_shapes,
                            self_collision=pairs, backend=backend)
    controller = make_controller(barriers, learner, **(filter_kwargs or {}))
    q0 = np.asarray(state.q, dtype=np.float64)
    policy = make_robot_policy(agent, chain, q0, seed)
    bridge = Bridge(robot, model, barriers, controller, policy, obstacles, limits, torques,
                    budget=budget, cost=cost, learn=learner != "none",
                    background_fit=background_fit)
    bridge.kinematics_error = checked
    return bridge


def run_simulated(seconds: float, *, agent: str = "nominal", learner: str = "none",
                  realtime: bool = True, budget: float = 0.9e-3, torque_error=0.0,
                  robot_kwargs: dict | None = None,
                  filter_kwargs: dict | None = None,
                  self_collision: bool | None = None, seed: int = 0) -> BridgeReport:
    """Run the bridge for ``seconds`` against a
    :class:`~afvsgp_gym.robots.simulated.SimulatedFranka` (``robot_kwargs``: its arguments;
    by default a 1 kg payload the served model does not know and the simulation's moving
    sphere; ``obstacles``: specs or the envs' dicts of any type); cost from the stand-in's
    true state (the arm touching itself included), recorded in the loop and checked after
    it (:class:`~afvsgp_gym.robots.simulated.CostLog`); ``self_collision`` and ``seed`` as
    :func:`build_bridge`'s."""
    from afvsgp_gym.robots.simulated import SimulatedFranka, Torques

    robot = SimulatedFranka(realtime=realtime, **(robot_kwargs or {}))
    bridge = build_bridge(robot, robot.load_model(), Torques, chain=robot.kinematics,
                          obstacle_radii=[o.radius for o in robot.obstacles],
                          obstacles=robot.obstacle_estimate, limits=robot.joint_limits,
                          agent=agent, learner=learner, spheres=robot.spheres, budget=budget,
                          cost=robot.cost_log(), torque_error=torque_error,
                          filter_kwargs=filter_kwargs,
                          obstacle_shapes=[o.shape for o in robot.obstacles],
                          self_collision=self_collision, seed=seed)
    report = bridge.run(seconds)
    report.lost_commands = robot.lost_commands
    return report


def static_obstacles(spheres: Sequence[Sequence[float]]) -> tuple[list[float], Callable]:
    """``(radii, callback)`` of fixed spheres ``(x, y, z, r)`` in the robot's base frame
    (virtual obstacles for a first run on hardware; none: the joint limits only)."""
    arr = np.asarray(spheres, dtype=np.float64).reshape(-1, 4)
    if not np.isfinite(arr).all() or np.any(arr[:, 3] <= 0):
        raise ValueError(f"obstacles must be (x, y, z, r) with r > 0. Got: {spheres!r}")
    est = ObstacleEstimate(arr[:, :3], np.zeros((len(arr), 3)), np.zeros((len(arr), 3)))
    return arr[:, 3].tolist(), lambda t: est


def obstacle_specs(obstacles: Sequence) -> list[ObstacleSpec]:
    """Virtual obstacles as specs: each entry an :class:`~afvsgp_gym.envs.scenario.ObstacleSpec`,
    one of the envs' ``obstacles=`` dicts (``"type"`` ``"sphere"``, ``"box"``, ``"capsule"``
    or ``"plane"``; a moving one starts after the tracker's warm-up, 2 s, by default) or a
    fixed sphere ``(x, y, z, r)``; ValueError naming ``obstacles[i]`` (and its key)."""
    entries = []
    for i, ob in enumerate(obstacles):
        if isinstance(ob, ObstacleSpec | Mapping):
            entries.append(ob)
            continue
        arr = np.asarray(ob, dtype=np.float64) if _is_numeric(ob) else None
        if arr is None or arr.shape != (4,):
            raise ValueError(f"obstacles[{i}] must be an ObstacleSpec, a dict with a 'type' "
                             f"or (x, y, z, r). Got: {ob!r}")
        entries.append({"type": "sphere", "position": arr[:3].tolist(), "radius": arr[3]})
    return parse_obstacles(entries, 3, WARMUP_SECONDS, OBSTACLE_TYPES) if entries else []


def _is_numeric(value) -> bool:
    """``value`` converts to a float array (not ragged, no strings)."""
    try:
        np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return True


def scripted_obstacles(specs: Sequence[ObstacleSpec]) -> Callable[[float], ObstacleEstimate]:
    """The perception callback of virtual obstacles: their reference points' state at ``t``
    (s since the run's first state), exact; one estimate for all ticks when all are static."""
    if not specs:
        return static_obstacles([])[1]
    if all(ob.duration == 0.0 for ob in specs):
        fixed = ObstacleEstimate(*(np.array(x) for x in zip(*(ob.state(0.0) for ob in specs),
                                                           strict=True)))
        return lambda t: fixed

    def callback(t: float) -> ObstacleEstimate:
        return ObstacleEstimate(*(np.array(x) for x in zip(*(ob.state(t) for ob in specs),
                                                           strict=True)))

    return callback


def run_robot(host: str, seconds: float, *, obstacles: Sequence = (),
              agent: str = "hold", learner: str = "none", budget: float = 0.9e-3,
              torque_error=0.0, filter_kwargs: dict | None = None,
              self_collision: bool | None = None, seed: int = 0) -> BridgeReport:
    """Run the bridge for ``seconds`` on the robot at ``host`` (pylibfranka, Franka's DH
    table and the Panda's datasheet limits) with virtual ``obstacles`` (:func:`obstacle_specs`:
    specs, the envs' dicts of any type or fixed spheres ``(x, y, z, r)``); ``self_collision``
    and ``seed`` as :func:`build_bridge`'s."""
    specs = obstacle_specs(obstacles)  # (ValueError before connecting)
    robot, model, torques = connect(host)
    bridge = build_bridge(robot, model, torques, chain=FRANKA_PANDA,
                          obstacle_radii=[ob.radius for ob in specs],
                          obstacles=scripted_obstacles(specs), limits=panda_limits(),
                          agent=agent, learner=learner, budget=budget,
                          torque_error=torque_error, filter_kwargs=filter_kwargs,
                          obstacle_shapes=[ob.shape for ob in specs],
                          self_collision=self_collision, seed=seed)
    return bridge.run(seconds)
