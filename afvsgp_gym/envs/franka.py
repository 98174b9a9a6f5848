"""Franka Panda end-effector tracking past obstacles with a hidden model mismatch."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import replace
from typing import Any, NamedTuple

import mujoco
import numpy as np
from gymnasium import spaces
from gymnasium.envs.mujoco import MujocoEnv

from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs import scenes
from afvsgp_gym.envs.base import (
    NOMINAL_MODELS,
    SCENARIOS,
    ObstacleTask,
    keyword_defaults,
    named_arguments,
)
from afvsgp_gym.envs.braking import admissible_share
from afvsgp_gym.envs.joint_limits import (
    FRANKA_MAX_ACCELERATION,
    FRANKA_MAX_SPEED,
    FRANKA_MAX_TORQUE_RATE,
    JointLimits,
    arm_layout,
    joint_projection,
    limit_calibration,
)
from afvsgp_gym.envs.perception import (
    JointEncoders,
    ObstacleCamera,
    Perception,
    Pushes,
    pair_covariance,
)
from afvsgp_gym.envs.primitives import Plane, pair_barriers, stack_shapes
from afvsgp_gym.envs.safety_spheres import (
    PANDA_ARM_SPHERES,
    PANDA_BASE_SPHERES,
    end_effector_sphere,
    parse_spheres,
    sphere_arrays,
)
from afvsgp_gym.envs.scenario import (
    OBSTACLE_TYPES,
    CyclicReference,
    ObstacleSpec,
    dot3,
    parse_obstacles,
    sphere_barrier,
    sphere_barriers,
)
from afvsgp_gym.envs.self_collision import (
    PANDA_SELF_COLLISION_SPHERES,
    SelfCollisionPairs,
    SelfPairGeometry,
    chain_index,
)
from afvsgp_gym.types import BarrierLayout, BarrierSet
from afvsgp_gym.validation import check_choice, check_real

_BAD_WARNINGS = np.array(
    [
        int(mujoco.mjtWarning.mjWARN_BADQACC),
        int(mujoco.mjtWarning.mjWARN_BADQPOS),
        int(mujoco.mjtWarning.mjWARN_BADQVEL),
    ]
)


#: The Franka env's scenarios: the shared ones and the scenes of several typed obstacles
#: (:mod:`afvsgp_gym.envs.scenes`).
FRANKA_SCENARIOS = (*SCENARIOS, "tabletop", "shelf")


class StateView(NamedTuple):
    """One view of the state: the joint state (an ``MjData`` after ``mj_forward``), the
    safety spheres' and end-effector's kinematics, every barrier's geometry, the obstacle
    states ``(p, v, a)`` and the self-collision pairs' geometry (None without them). The env
    keeps the true view and the sensed one (the same object when it senses exactly)."""

    data: mujoco.MjData
    spheres: tuple[np.ndarray, ...]
    ee: tuple[np.ndarray, np.ndarray]
    geometry: tuple[np.ndarray, ...]
    obstacle_states: list
    self_pairs: SelfPairGeometry | None = None


class FrankaObstacleEnv(ObstacleTask, MujocoEnv):
    r"""Franka Panda (torque control) tracking a cyclic end-effector reference past obstacles.

    ## Description
    The 7-DoF Panda of ``gymnasium_robotics`` (see :mod:`afvsgp_gym.envs.franka_model`) with
    motor actuators, a fixed gripper and the robot's own gravity compensation of its
    *catalogue* model. The true plant differs from the catalogue: a ``payload_mass`` at the
    flange (not compensated), link masses and inertias scaled by per-link factors drawn from
    ``mass_scale`` with ``plant_seed``, joint ``damping``, ``friction`` (frictionloss) and
    rotor ``armature``. The end-effector (site ``end_effector`` on the gripper axis between
    the finger pads, 4-5 cm above the fingertips) tracks the reference of paper Fig. 3; the
    safety filter keeps the whole arm out of the obstacles.

    Gravity compensation, as with the real robot's torque interface: commanded torques act on
    top of the robot's compensation of its catalogue model. Each link of the true plant gets
    MuJoCo ``gravcomp = m_catalogue / m_true`` (set in the MjSpec before compiling), the
    payload gravcomp 0, so ``(m_true - m_catalogue) g`` per link and the full payload weight
    remain as unknown residual gravity.

    Physics: MuJoCo step ``physics_dt`` = 2 ms (Euler, implicit joint damping), ``frame_skip``
    = 2, so the control period ``dt`` = 4 ms (250 Hz); ``render_fps`` = 250.

    ## Barriers (paper eqs. 44-46)
    ``safety_spheres`` fixes spheres to the arm's bodies: ``"arm"`` (default) the 21 spheres
    of :data:`~afvsgp_gym.envs.safety_spheres.PANDA_ARM_SPHERES`, which cover links 1-7, the
    hand and the fingers; ``"ee"`` the paper's single sphere of radius ``ee_radius`` around the
    end-effector site; or a list of ``(body, offset, radius)``. Every (sphere ``s``, obstacle
    ``o``) pair is a barrier (``n_barriers`` = spheres x obstacles, obstacle-major order,
    names in ``barrier_names``), ``h = |p_s - p_o| - (r_s + r_o)``, relative degree 2:
    ``h'' = n.(J_s q'' + J_s' q' - a_o) + (|v_rel|^2 - (n.v_rel)^2)/|d|``, ``n = d/|d|``,
    with ``J_s`` the Jacobian of the sphere centre. With ``q'' = q''_0 + M^-1 diag(action_scale)
    u`` (``q''_0``: acceleration at u = 0 from passive, bias, residual gravity and joint-limit
    forces), ``barrier_terms(model)`` gives ``lf = n.(J_s q''_0 + J_s' q' - a_o) + curvature``
    and ``lg = n' J_s M^-1 diag(action_scale)``:

    - ``"true"``: the true plant (for evaluation / oracle only).
    - ``"nominal"`` by ``nominal_model``: ``"zero"`` lf = lg = 0 (paper section VI; the
      derivatives [h, h'] are still measured); ``"kinematic"`` kinematics and obstacle motion
      known: lf = n.(J_s' q' - a_o) + curvature, lg = 0; ``"perturbed"`` a second model with
      the catalogue parameters (no payload, link masses and inertias unscaled, no damping or
      friction, full gravity compensation; the rotor armature, a datasheet value that
      dominates the wrist joints' inertia, is the plant's); ``"exact"`` the true plant
      (delta_b_true = 0).
    - features ``xi = [q (7), q' (7), p_s - p_o (3), v_s - v_o (3)]``, feature_dim 20
      (the paper's b = 20).

    Boxes, capsules and planes (``obstacles`` with a ``"type"``, below) give the same terms
    with ``h = d(p_s - c) - r_s``, ``d`` the primitive's exact signed distance
    (:mod:`~afvsgp_gym.envs.primitives`; ``c`` its centre, or a plane's point, moved by the
    obstacle's translation), ``n`` the unit normal of the closest feature and the curvature
    ``v_rel' H v_rel`` of its Hessian (0 on a face or a plane); their features hold, in
    place of ``p_s - p_o``, ``n d``: the offset of the sphere centre from the closest surface
    point (a plane's reference point is arbitrary; for a sphere obstacle ``p_s - p_o`` stays,
    its centre being its feature).

    Friction (frictionloss) and joint-limit forces come from MuJoCo's constraint solver and are
    evaluated at u = 0, so with ``friction > 0`` the split into lf and lg is exact only while
    the joints slide (static friction couples them); ``friction=0`` makes it exact.
    ``"true_robust"``: the true terms with ``lf`` lowered by the friction bound of
    ``true_terms_error_bound`` (``2 sum_j |n' J_s M^-1|_j f_j``), for an oracle safe under
    friction (``SafetyFilter(..., learner="oracle", oracle_terms="true_robust")``).

    With ``self_collision`` (on by default with ``safety_spheres="arm"``, the default; off
    with other sphere sets, which its pairs are not chosen for) the arm's own links are kept
    apart too: after the obstacle barriers come ``n_self_collision_barriers``
    barriers, one per pair of :data:`~afvsgp_gym.envs.self_collision.PANDA_SELF_COLLISION_PAIRS`
    (93: spheres on links at least two apart in the chain, the base's two spheres of
    :data:`~afvsgp_gym.envs.safety_spheres.PANDA_BASE_SPHERES` included, that can come within
    0.01 m of each other within the joint ranges and do not overlap at the ready pose;
    :mod:`~afvsgp_gym.envs.self_collision` says how they were chosen), named
    ``"link1[0]/link7[14]"`` or, with the base, ``"link7[20]/link0[22]"``. Each is the
    obstacle pair's barrier with the second sphere in the obstacle's place (a base sphere
    does not move: zero velocity, Jacobian and acceleration): ``h = |p_a - p_b| - r_a - r_b``,
    ``lf = n.(a_a - a_b) + curvature`` with ``a_s = J_s q''_0 + J_s' q'``, ``lg = n'(J_a -
    J_b) M^-1 diag(action_scale)``, from the same models (``"kinematic"``: ``lg = 0``,
    ``"zero"``: both 0), features ``[q, q', p_a - p_b, v_a - v_b]``, one learner each, and the
    obstacle pairs' suggested filter settings.

    With ``limit_barriers`` (default) the robot's own limits follow the obstacle (and
    self-collision) barriers: per joint a lower and an upper range barrier (relative
    degree 2, ``range_margin`` rad inside the model's joint range) and a lower and an upper
    speed barrier (relative degree 1, ``speed_margin`` rad/s below the datasheet speed),
    28 in all (:mod:`afvsgp_gym.envs.joint_limits`); their ``lf``/``lg`` are ``+-(q''_0,
    M^-1 diag(action_scale))`` of joint j in the perturbed and true models and 0 in the
    zero and kinematic ones (joint accelerations are dynamics), and the four of a joint share
    one learner (``barrier_layout``). Their features are ``[q, q', 0 (6)]``.

    Suggested filter settings (``filter_defaults``, read by ``SafetyFilter`` under the
    caller's options): activation distances (0.15 m obstacles, 0.3 rad ranges, always for
    speeds), braking decelerations (5 m/s^2 obstacles, the datasheet's acceleration limits
    for the ranges: the first class-K function is then the braking curve of
    :func:`~afvsgp_gym.cbf.hocbf.braking_alpha`, so the approach speed never exceeds what the
    torque limits can stop), a first gain of ``SPEED_GAIN`` = 25 1/s for the speed barriers,
    and the warm-up exploration around the brake (``warmup_exploration="backup"``, noise 0.2).
    The speed barriers, always in the program, bound every joint's acceleration by
    ``a (2 V_j)``, so no barrier outside the program can cross its activation margin within
    one control period.

    ## Action Space
    ``Box(-1, 1, (7,), float32)``: joint torques ``tau = u * tau_max``, tau_max = (87, 87, 87,
    87, 12, 12, 12) Nm, added to the robot's gravity compensation (``action_scale`` =
    tau_max). With ``normalize_action=False`` the action is the torque itself,
    ``Box(-tau_max, tau_max)`` (``action_scale`` = 1), and ``lg`` is per Nm. Out-of-range
    actions are clipped; NaN/inf or a wrong shape raise ValueError before anything reaches
    MuJoCo.

    ## Observation Space
    ``Box(float32)`` of size ``29 + 6 n_obstacles`` (values clipped to the bounds):

    | Slice | Observation | Min | Max | Name in XML | Unit |
    |---|---|---|---|---|---|
    | 0:7 | joint angles q | -2 pi | 2 pi | robot:panda0_joint1..7 | rad |
    | 7:14 | joint velocities q' | -20 | 20 | robot:panda0_joint1..7 | rad/s |
    | 14:17 | end-effector position | -3 | 3 | site end_effector | m |
    | 17:20 | end-effector velocity | -10 | 10 | site end_effector | m/s |
    | next 3n | obstacle centres (a plane: its point) | -5 | 5 | body obstacle<i> | m |
    | next 3n | obstacle velocities | -5 | 5 | | m/s |
    | next 3 | reference position | -3 | 3 | body reference | m |
    | next 3 | reference velocity | -10 | 10 | | m/s |
    | next 3 | reference acceleration | -50 | 50 | | m/s^2 |

    ## Rewards
    ``reward = reward_tracking + reward_ctrl``, ``reward_tracking = -tracking_weight
    |p_ee - r|`` (m), ``reward_ctrl = -control_weight |u|^2``; terms in ``info``.

    ## Cost (Safety-Gymnasium convention)
    ``info["cost"] = 1.0`` when some obstacle barrier has h < 0 (``info["h"] < 0``), some arm
    collision geom (links 1-7, hand, fingers) touches an obstacle (``mj_geomDistance`` < 0,
    ``info["collision"]``), even with every h >= 0, or a joint is beyond the robot's own
    limits, as the real controller would abort on (``info["limit_violation"]``): at its range
    stop (``q_j <= lo_j`` or ``>= hi_j``, the model's range) or above its datasheet speed
    (2.175 rad/s joints 1-4, 2.61 rad/s joints 5-7); with ``check_acceleration`` also above
    the datasheet acceleration limits (15, 7.5, 10, 12.5, 15, 20, 20 rad/s^2, measured over a
    control period) and with ``check_torque_rate`` above 1000 Nm/s of commanded torque. The
    limits count whether or not ``limit_barriers`` are on. So does the arm touching itself
    or its base (``info["self_contact"]``), whether or not ``self_collision`` is on
    (:attr:`COST_VERSION` 1; before it, self-contact was reported but not counted).

    ## Starting State
    The ready pose ``q = (0, -0.785, 0, -2.356, 0, 0, 0.785)`` (end-effector at the reference
    centre, about (0.307, 0, 0.487) m, hand down) plus uniform noise of +-``reset_noise`` rad,
    at rest.

    ## Episode End
    Terminated when the simulation goes unstable (non-finite state or a MuJoCo bad-state
    warning; ``info["unstable"] = True``). Truncation by ``TimeLimit``: 4000 steps (16 s).

    ## Info
    ``cost``, ``h`` (min over the obstacle barriers, m), ``h_per_barrier`` (every barrier, in
    its own unit), ``collision`` (contact), ``limit_violation``, ``delta_b_true`` (true minus
    nominal highest derivative per barrier for the applied action at the pre-step state),
    ``tracking_error`` (|p_ee - r|, m), ``self_contact`` (two collision geoms of the robot
    on links at least two apart in the chain touch, the hand and fingers counting as one link
    after link7 and the base, link0, as the link before link1 (its neighbour); pairs touching
    at the ready pose would be left out: none do), ``reference_h`` (clearance of an
    ``ee_radius`` sphere at the reference point from every obstacle: the reference is "away
    from the obstacle" when it is >= 0.05 m), ``unstable``, ``time``, ``reward_tracking``,
    ``reward_ctrl``.

    ## Scenarios (c = reference centre, y = axis of the cyclic motion)
    Reference: ``c + a(t) sin(2 pi t / 4 s)`` along y, amplitude 0.04 m during the
    ``warmup_steps`` (500 = 2 s), ramped to 0.28 m over 1 s; static scenario: turns to z at
    ``switch_time`` (10 s). Peak reference speed 0.44 m/s, acceleration 0.7 m/s^2.

    - ``"static"``: sphere r = 0.05 m at c + (0, 0.20, -0.07): the full y motion passes 7 cm
      above its centre, inside the safe set of the hand's spheres, so the filter must act; the
      warm-up motion stays clear of it.
    - ``"dynamic"``: sphere r = 0.05 m rests at c + (0.5, 0.15, -0.07) during warm-up, then
      moves in -x onto the path, c + (0, 0.15, -0.07), with peak speed ``obstacle_speed``
      (0.15 m/s) and stays there. No switch unless set.
    - ``"random"``: static or dynamic with radius in [0.04, 0.07] m, position along y in
      [r + 0.15, 0.24] m on either side, offset in z in [-0.09, -0.06] m and x in +-0.02 m,
      approach from +x or from outside along y at 0.3-0.5 m, peak speed in [0.05, 0.2] m/s
      and an optional switch, drawn per reset.
    - ``"tabletop"`` (:mod:`~afvsgp_gym.envs.scenes`): a table (a plane at the mount,
      z = 0), 10 clutter obstacles (4 boxes, 3 capsules lying with a drawn yaw, 3 spheres;
      sizes, yaws and places drawn per reset, each one's bounding ball outside the arm's swept
      volume under the tracker, :data:`~afvsgp_gym.envs.scenes.ARM_SWEEP`, so near the path
      but off it and clear of the warm-up) and a forearm: a capsule (r = 0.04 m, half length
      0.15 m) along x that comes in 0.5 m from +x, 0-1 s after the warm-up at 0.15-0.25 m/s,
      to rest across the path's end, c + (0, +-[0.17, 0.24], [-0.09, -0.06]), and stops
      earlier once a safety sphere is 5 cm from it (it yields, ``ObstacleSpec.yield_distance``).
      12 obstacles.
    - ``"shelf"``: a table and a shelf of five boxes open towards the robot (lower and upper
      boards 0.14 m under and 0.33 m over c, side walls at y = +-0.2 m, the opening 0.2 m and
      the back wall 0.33 m in front of c, 3 cm thick); the reference moves along x about
      c + (0.1, 0, 0) with amplitude 0.2 m, into the opening and out (no switch unless set):
      the hand would reach the back wall. Static. 6 obstacles.

    With the exact model and no joint friction a CBF-filtered run keeps every barrier h >= 0
    with no arm contact in every scenario and seed tested (tests/envs/test_franka.py,
    test_franka_scenes.py, docs/safety.md); with friction the true terms are not exact
    (above) and it does not always (docs/safety.md, "What this does not show").

    ## Arguments
    | Parameter | Default | Description |
    |---|---|---|
    | scenario | "static" | "static", "dynamic", "random", "tabletop", "shelf" |
    | nominal_model | "zero" | "zero", "kinematic", "perturbed", "exact" |
    | safety_spheres | "arm" | "arm", "ee" or a list of (body, offset, radius) |
    | payload_mass | 1.0 | kg at the flange, not gravity compensated |
    | mass_scale | (0.9, 1.3) | per-link mass/inertia factor range (or one float) |
    | damping | 1.0 | joint damping, Nm s/rad (true plant) |
    | friction | 0.0 | joint frictionloss, Nm (true plant) |
    | armature | 0.1 | rotor inertia, kg m^2 (true plant) |
    | plant_seed | 0 | seed of the per-link mass factors |
    | physics_dt, frame_skip | 0.002, 2 | MuJoCo step (s) and steps per action |
    | ee_radius | 0.05 | m, the "ee" sphere (and ``reference_h``) |
    | obstacles | None | list of dicts (type, position, sizes[, start, start_time, speed]) |
    | obstacle_speed | 0.15 | m/s, dynamic scenario |
    | switch_time | None | s; None = 10 s static, none otherwise |
    | warmup_steps | 500 | steps with obstacles far away (>= 250) |
    | tracking_weight, control_weight | 1.0, 0.01 | reward weights |
    | reset_noise | 0.01 | rad |
    | normalize_action | True | action in [-1, 1] (tau = u tau_max); False: action = tau in Nm |
    | brake_frequency | 50.0 | 1/s, ``backup_action``'s stop-and-hold bandwidth |
    | brake_hold_memory | 0.1 | s, the brake's hold point outlives feasible gaps this short |
    | brake_hold_slack | 0.0 | rad, a saturated brake keeps its hold point this near |
    | limit_barriers | True | joint range and speed barriers after the obstacle ones |
    | self_collision | None | the arm's own links kept apart (None: on with the "arm" spheres) |
    | range_margin, speed_margin | 0.1, 0.4 | rad, rad/s: the limit barriers' margins |
    | check_acceleration, check_torque_rate | False, False | optional limit checks (Cost) |
    | obstacle_noise, obstacle_rate, obstacle_delay | 0.0, None, 0.0 | m, Hz, s: the camera |
    | velocity_noise, position_noise | 0.0, 0.0 | rad/s, rad: the joint encoders |
    | push | None | ``{"force": N, "duration": s, "rate": 1/s}``: random pushes on the links |
    | render_mode, width, height | None, 480, 480 | "rgb_array", "depth_array", "human" (display) |

    Custom ``obstacles`` replace the scenario's (the reference stays): each dict gives the
    final ``position`` and its ``"type"``'s sizes; with ``start`` the obstacle rests there
    and moves (translation only) to ``position`` from ``start_time`` (default: the end of the
    warm-up) at peak ``speed`` (m/s, default 0.2). Keeping them clear of the warm-up motion
    is then up to the caller. The types and their keys (m; a bad entry raises ValueError
    naming ``obstacles[i]['key']``):

    - ``"sphere"`` (the default): ``radius``.
    - ``"box"``: ``half_sizes`` (3,), orientation ``quat`` (w, x, y, z) or ``rotation``
      (3, 3; its columns the box's axes), default axis-aligned.
    - ``"capsule"``: ``radius``, ``half_length`` and its axis as ``axis`` (3,) or ``quat``
      (local z, as MuJoCo's capsule), default vertical.
    - ``"plane"``: ``position`` a point of it and ``normal`` (3,) pointing out of the
      obstacle (a table: ``normal`` up); static only. The barrier and the contact check take
      the infinite half-space; the drawn rectangle is 2 m wide.

    The base (link0) has no safety sphere against obstacles (its spheres serve the
    self-collision barriers only) and is not in the obstacle contact check, so a table the
    robot stands on is a plane at or below the mount (z <= 0); the lowest safety spheres
    (link1's) reach 0.11 m above it, and a plane above that violates their barriers at every
    pose. The obstacle camera (``obstacle_noise``, ``obstacle_rate``, ``obstacle_delay``) and
    an estimate's covariance (:meth:`set_obstacle_estimate`) model sphere centres only: with
    another type they raise ValueError (the joint encoders and pushes work with every type).

    ## Version History
    - v0: ``self_collision`` on by default with the arm's spheres, and self-contact counts
      as cost (:attr:`COST_VERSION` 1; issue 46).
    - v0: ``self_collision`` barriers (then opt-in) and ``info["self_contact"]``, the base
      included in both (issue 46).
    - v0: the ``"tabletop"`` and ``"shelf"`` scenes (issue 46) joined the scenarios.
    - v0: initial version; whole-arm safety spheres (``safety_spheres="arm"``) are the
      default, contacts count as cost; the joint range and speed limits count as cost and
      have barriers (``limit_barriers``), and the brake stops and holds every joint
      (``brake_frequency``).
    """

    # "human" needs a display (GLFW window); headless machines render offscreen (MUJOCO_GL=egl)
    metadata = {
        "render_modes": ["rgb_array", "depth_array"]
        + (["human"] if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") else []),
        "render_fps": 250,
    }

    AMPLITUDE, WARMUP_AMPLITUDE, PERIOD = 0.28, 0.04, 4.0
    #: Suggested activation distance of the safety filter for the obstacle barriers (m):
    #: barriers farther than this (and not approaching faster than alpha_1 of it) stay out of
    #: the cone program. The joint-limit barriers' are ``RANGE_ACTIVATION`` (rad) and
    #: ``SPEED_ACTIVATION`` (rad/s): :attr:`activation_distance` gives one per barrier.
    OBSTACLE_ACTIVATION = 0.15
    RANGE_ACTIVATION = 0.3
    SPEED_ACTIVATION = float("inf")
    #: Braking deceleration suggested for the obstacle barriers (m/s^2) and the joint range
    #: barriers (rad/s^2, per joint: the datasheet's acceleration limits): the filter's
    #: first class-K function is the braking curve of this deceleration
    #: (:func:`~afvsgp_gym.cbf.hocbf.braking_alpha`), which the torque limits can always
    #: produce (benchmarks/configs/adversarial.toml, docs: "Any policy").
    OBSTACLE_DECELERATION = 5.0
    RANGE_DECELERATION = FRANKA_MAX_ACCELERATION
    #: Gain of the joint speed barriers' class-K function (1/s): ``q'' <= a (V - q')``, a
    #: tenth of the control rate (the obstacle and range barriers keep ``alpha``'s a_1).
    SPEED_GAIN = 25.0
    #: The brake yields to moving obstacles (:meth:`backup_action`): pairs closer than
    #: ``EVADE_DISTANCE`` (m) whose obstacle approaches the sphere are given way at
    #: ``EVADE_FACTOR`` times the approach speed, with joint speeds up to ``EVADE_SPEED_SHARE``
    #: of the datasheet's.
    EVADE_DISTANCE, EVADE_FACTOR, EVADE_SPEED_SHARE = 0.1, 1.5, 0.5
    #: m: a pair given way within the brake's hold memory (``brake_hold_memory``, at least
    #: the last control period) is given way until this much beyond ``EVADE_DISTANCE`` (a
    #: pair hovering at the distance switched the give-way on and off every few periods, and
    #: the brake saturated at each switch).
    EVADE_HYSTERESIS = 0.01
    #: The brake's behaviour (:meth:`backup_action`), written into every episode record
    #: (``brake_version``) so that results tell which brake they ran with. 1: the hold point
    #: kept for ``brake_hold_memory`` while the obstacles stand still, the give-way holding
    #: every other near pair from closing in and keeping a pair until ``EVADE_HYSTERESIS``
    #: beyond ``EVADE_DISTANCE`` (920d688). Bump it with any change of the brake's actions.
    BRAKE_VERSION = 1
    #: What ``info["cost"]`` counts; episode records carry it. 1: also the arm touching
    #: itself or its base (``info["self_contact"]``); 0 (before): obstacles and limits only.
    COST_VERSION = 1
    #: Sphere pairs (obstacle and self-collision) above which ``SafetyFilter``'s default
    #: learner is the shared one where the prior knows the dynamics (:meth:`suggested_learner`):
    #: one obstacle on the 21 arm spheres, where the two learners' steps are equal; from two
    #: obstacles on the shared one's is the faster (``benchmarks.scale --crossover``)
    SHARED_LEARNER_PAIRS = 21
    #: m: an obstacle that moved more than this (as sensed) since the brake's last period
    #: voids its hold point (``backup_action``; ``brake_hold_memory``).
    HOLD_WORLD_TOLERANCE = 1e-4
    #: Warm-up exploration suggested to the filter: around the brake (the policy does not act
    #: until the learners are fitted, so nothing it proposes can break the limits then), with
    #: a noise of 0.2 of the torque range (white torque noise of 0.3, the method's, drives the
    #: light, folded joint 1 to its speed limit).
    WARMUP_FILTER_DEFAULTS: dict[str, Any] = {"warmup_exploration": "backup",
                                              "exploration_noise": 0.2}
    #: AFVSGP settings suggested to ``SafetyFilter`` (under the user's ``learner_kwargs``) when
    #: the sphere set has several spheres (one learner each): M = 30 inducing points and a
    #: window of P = 500 samples instead of the method's 40 and 1000 (the evidence:
    #: docs/filter.md, "Defaults that differ from the paper"). One sphere (the paper's
    #: "ee") keeps the method's settings.
    ARM_LEARNER_DEFAULTS: dict[str, dict[str, Any]] = {"afvsgp": {"num_inducing": 30,
                                                                   "window": 500}}

    @named_arguments
    def __init__(
        self,
        scenario: str = "static",
        *,
        nominal_model: str = "zero",
        safety_spheres: str | Sequence = "arm",
        payload_mass: float = 1.0,
        mass_scale: float | tuple[float, float] = (0.9, 1.3),
        damping: float = 1.0,
        friction: float = 0.0,
        armature: float = 0.1,
        plant_seed: int = 0,
        physics_dt: float = 0.002,
        frame_skip: int = 2,
        ee_radius: float = 0.05,
        obstacles: Sequence[dict] | None = None,
        obstacle_speed: float = 0.15,
        switch_time: float | None = None,
        warmup_steps: int = 500,
        tracking_weight: float = 1.0,
        control_weight: float = 0.01,
        reset_noise: float = 0.01,
        normalize_action: bool = True,
        brake_frequency: float = 50.0,
        brake_hold_memory: float = 0.1,
        brake_hold_slack: float = 0.0,
        limit_barriers: bool = True,
        self_collision: bool | None = None,
        range_margin: float = 0.1,
        speed_margin: float = 0.4,
        check_acceleration: bool = False,
        check_torque_rate: bool = False,
        obstacle_noise: float = 0.0,
        obstacle_rate: float | None = None,
        obstacle_delay: float = 0.0,
        velocity_noise: float = 0.0,
        position_noise: float = 0.0,
        push: dict | None = None,
        render_mode: str | None = None,
        width: int = 480,
        height: int = 480,
    ) -> None:
        self.scenario = check_choice("scenario", scenario, FRANKA_SCENARIOS)
        self.nominal_model = check_choice("nominal_model", nominal_model, NOMINAL_MODELS)
        payload_mass = check_real(payload_mass, "payload_mass", low=0.0)
        damping = check_real(damping, "damping", low=0.0)
        friction = check_real(friction, "friction", low=0.0)
        armature = check_real(armature, "armature", low=0.0)
        reset_noise = check_real(reset_noise, "reset_noise", low=0.0)
        physics_dt = check_real(physics_dt, "physics_dt", low=0.0, low_open=True)
        ee_radius = check_real(ee_radius, "ee_radius", low=0.0, low_open=True)
        obstacle_speed = check_real(obstacle_speed, "obstacle_speed", low=0.0, low_open=True)
        n_skip = int(frame_skip)
        if n_skip < 1:
            raise ValueError(f"frame_skip must be >= 1, got {frame_skip}")
        self.warmup_steps = int(warmup_steps)
        if self.warmup_steps < 0:
            raise ValueError(f"warmup_steps must be >= 0, got {warmup_steps}")
        st = switch_time
        if st is not None and not (float(st) > 0):
            raise ValueError(f"switch_time must be > 0 or None, got {st}")
        self._switch_time_arg = None if st is None else float(st)
        self.ee_radius = self.tracking_radius = float(ee_radius)
        self.obstacle_speed = float(obstacle_speed)
        self.tracking_weight = float(tracking_weight)
        self.control_weight = float(control_weight)
        self.reset_noise = float(reset_noise)
        self.normalize_action = bool(normalize_action)
        self.limit_barriers = bool(limit_barriers)
        if self_collision is not None and not isinstance(self_collision, bool | np.bool_):
            raise ValueError(
                f"self_collision must be True, False or None. Got: {self_collision!r}")
        self._self_collision_arg = None if self_collision is None else bool(self_collision)
        range_margin = check_real(range_margin, "range_margin", low=0.0)
        speed_margin = check_real(speed_margin, "speed_margin", low=0.0)
        self.perception = Perception(obstacle_noise, obstacle_rate, obstacle_delay,
                                     velocity_noise, position_noise, push)
        physics_dt = float(physics_dt)
        self._control_dt = physics_dt * n_skip
        self._user_obstacles = (
            None
            if obstacles is None
            else parse_obstacles(obstacles, 3, self.warmup_steps * self._control_dt,
                                 OBSTACLE_TYPES)
        )
        # the obstacles the geoms are built from: the user's, or a scene's (the tabletop's at
        # their largest sizes: a drawn scene resizes the geoms per reset), or None (a sphere)
        self._layout_obstacles = self._user_obstacles or self._scene_layout()
        self._check_camera_obstacles()
        self.plant = self._plant_parameters(mass_scale, plant_seed, payload_mass, damping,
                                            friction, armature)
        layout = self._layout_obstacles
        n_obs = 1 if layout is None else len(layout)
        radii = (0.05,) * n_obs if layout is None else tuple(o.radius for o in layout)
        if self.scenario == "random" and layout is None:
            radii = (0.07,)  # drawn radii <= 0.07: the visual sphere is rescaled per reset
        geoms = () if layout is None else tuple(fm.obstacle_geom(o) for o in layout)
        self._scene = fm.SceneOptions(radii, self.ee_radius, physics_dt, geoms)
        if render_mode is not None:
            check_choice("render_mode", render_mode, self.metadata["render_modes"])
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self._control_dt))}
        self.n_obstacles = n_obs
        self.feature_dim = 20
        lim = np.concatenate(
            [np.full(7, 2 * np.pi), np.full(7, 20.0), np.full(3, 3.0), np.full(3, 10.0)]
            + [np.full(3 * n_obs, 5.0), np.full(3 * n_obs, 5.0)]
            + [np.full(3, 3.0), np.full(3, 10.0), np.full(3, 50.0)]
        )
        self._obs_high, self._obs_low = lim, -lim
        obs_space = spaces.Box(-lim.astype(np.float32), lim.astype(np.float32), dtype=np.float32)
        super().__init__(
            fm.asset_dir(),  # the model is assembled in _initialize_simulation
            n_skip,
            obs_space,
            render_mode=render_mode,
            width=int(width),
            height=int(height),
            default_camera_config={
                "distance": 1.5,
                "azimuth": 200.0,
                "elevation": -20.0,
                "lookat": np.array([0.3, 0.0, 0.45]),
            },
        )
        m = self.model
        self._site = m.site(fm.EE_SITE).id
        self._gear = m.actuator_gear[:, 0].copy()
        if self.normalize_action:
            self.action_scale = self._gear.copy()  # Nm per action unit
        else:
            self.action_scale = np.ones(7)
            self.action_space = spaces.Box(
                -self._gear.astype(np.float32), self._gear.astype(np.float32), dtype=np.float32
            )
        self._ctrl_per_action = self.action_scale / self._gear
        self.brake_frequency = check_real(brake_frequency, "brake_frequency", low=0.0,
                                          low_open=True)
        self.brake_hold_memory = check_real(brake_hold_memory, "brake_hold_memory", low=0.0)
        self._hold_memory_steps = int(round(self.brake_hold_memory / self._control_dt))
        self.brake_hold_slack = check_real(brake_hold_slack, "brake_hold_slack", low=0.0)
        self._brake_model: tuple[mujoco.MjModel, mujoco.MjData] | None = None
        self._hold: np.ndarray | None = None
        self._backup_step = -2
        self._hold_world: np.ndarray | None = None
        #: the control period of the last give-way and the pairs it gave way to
        self._giving_way: tuple[int, np.ndarray] = (-2, np.zeros(0, dtype=bool))
        self._yielding = False  # some obstacle may yield (set with the obstacles)
        self.joint_limits = JointLimits(
            m.jnt_range[:7, 0], m.jnt_range[:7, 1], FRANKA_MAX_SPEED, range_margin,
            speed_margin, FRANKA_MAX_ACCELERATION if check_acceleration else None,
            FRANKA_MAX_TORQUE_RATE if check_torque_rate else None)
        self._setup_spheres(safety_spheres)
        self._arm_geoms = fm.arm_collision_geoms(m)
        self._arm_rbound = m.geom_rbound[self._arm_geoms].copy()
        self._self_contact_pairs = self_contact_geom_pairs(self.model)
        self._obstacle_geoms = np.array([m.geom(f"obstacle{i}").id for i in range(n_obs)])
        # their orientations change per reset (the tabletop's clutter): the compiler's
        # "same frame as the body" shortcut would keep the compiled one in data.geom_xmat
        m.geom_sameframe[self._obstacle_geoms] = 0
        self._obstacle_mocap = np.array(
            [m.body_mocapid[m.body(f"obstacle{i}").id] for i in range(n_obs)]
        )
        self._ref_mocap = m.body_mocapid[m.body("reference").id]
        self.q_home = fm.Q_HOME.copy()
        d = mujoco.MjData(m)
        d.qpos[:] = self.q_home
        mujoco.mj_kinematics(m, d)
        self.reference_center = d.site_xpos[self._site].copy()
        if self.nominal_model == "perturbed":
            catalogue = fm.PlantParameters(armature=self.plant.armature)
            self.nominal_mj_model = fm.build_model(catalogue, self._scene)
            self.nominal_mj_data = mujoco.MjData(self.nominal_mj_model)
        else:
            self.nominal_mj_model = self.model if self.nominal_model == "exact" else None
            self.nominal_mj_data = None
        self._obstacle_key = None
        self._zeros: tuple[np.ndarray, np.ndarray] | None = None
        self._step_rates: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
        self._last_torque = np.zeros(7)
        self._setup_sensing()
        self._build_scenario(None)
        self._steps = 0
        self._invalidate_barriers()

    #: The keyword arguments and their defaults (from the signature; the ``## Arguments``
    #: table is tested against them).
    _DEFAULTS: dict[str, Any] = keyword_defaults(__init__)

    # ------------------------------------------------------------------ construction
    def _check_camera_obstacles(self) -> None:
        """The camera (and the estimate's covariance) model sphere centres only: refuse it
        with another obstacle type, naming the options set and the obstacle."""
        layout = self._layout_obstacles or ()
        shaped = [i for i, o in enumerate(layout) if o.shape is not None]
        per = self.perception
        if shaped and per.camera:
            names = [name for name, on in (("obstacle_noise", per.obstacle_noise > 0),
                                           ("obstacle_rate", per.obstacle_rate is not None),
                                           ("obstacle_delay", per.obstacle_delay > 0)) if on]
            i = shaped[0]
            raise ValueError(f"{', '.join(names)}: the obstacle camera senses sphere obstacles "
                             f"only, and obstacles[{i}] is a "
                             f"{layout[i].kind!r}; sense it exactly (leave "
                             f"obstacle_noise, obstacle_rate and obstacle_delay at their "
                             f"defaults)")

    def _setup_spheres(self, spec) -> None:
        """Resolve ``safety_spheres`` and the per-body buffers of the sphere kinematics."""
        m = self.model
        names = [m.body(i).name for i in range(m.nbody)]
        arm = [n for n in names if n.startswith("panda0_") and n != "panda0_link0"]
        if isinstance(spec, str):
            check_choice("safety_spheres", spec, ("arm", "ee"))
            spheres = PANDA_ARM_SPHERES if spec == "arm" else (end_effector_sphere(self.ee_radius),)
        else:
            spheres = parse_spheres(spec, arm)
        self.safety_spheres = spheres
        bodies, offsets, radii = sphere_arrays(spheres)
        self._sphere_body_ids = np.array([m.body(b).id for b in bodies])
        self._sphere_offsets = offsets
        self._sphere_offset_cols = np.ascontiguousarray(offsets[:, :, None])  # (S, 3, 1)
        self._sphere_radii = radii
        self._sphere_bodies = self._sphere_body_ids.tolist()
        n_s = len(spheres)
        self._n_pairs = n_s * self.n_obstacles
        self._self_pairs = self._self_collision_pairs(spec, spheres)
        self_names = (() if self._self_pairs is None
                      else self._self_pairs.names(PANDA_SELF_COLLISION_SPHERES))
        limits = self.joint_limits.names() if self.limit_barriers else ()
        self.n_barriers = self._n_pairs + len(self_names) + len(limits)
        self.barrier_names = tuple(
            f"{s.body.removeprefix('panda0_')}[{i}]/obstacle{o}"
            for o in range(self.n_obstacles)
            for i, s in enumerate(spheres)
        ) + self_names + limits
        # One-sphere shortcuts (the paper's "ee"), each giving the general path's numbers:
        # the sphere at the end-effector site is the site (MuJoCo's site_xpos is xmat @ pos +
        # xpos, the sum _sphere_centres forms; with one nonzero offset entry the order of the
        # sum cannot matter) and one pair is geometry in Python floats (sphere_barrier).
        site_pos = m.site_pos[self._site]
        at_site = (
            n_s == 1
            and self._sphere_bodies[0] == int(m.site_bodyid[self._site])
            and np.array_equal(offsets[0], site_pos)
            and np.count_nonzero(site_pos) <= 1
        )
        self._kinematics = self._site_kinematics if at_site else self._point_kinematics
        shaped = any(o.shape is not None for o in self._layout_obstacles or ())
        self._geometry_of = (
            self._one_pair_geometry if self._n_pairs == 1 and not shaped
            else self._pair_geometry
        )

    def _self_collision_pairs(self, spec, spheres) -> SelfCollisionPairs | None:
        """The self-collision pairs (``self_collision``; None: on exactly with the ``"arm"``
        spheres), chosen for those spheres and the base's, which stay where the model puts
        link0: ``self_collision=True`` with another sphere set raises ``ValueError`` naming
        both options. Sets :attr:`self_collision` to what was resolved."""
        arm = tuple(spheres) == PANDA_ARM_SPHERES
        wanted = self._self_collision_arg
        self.self_collision = arm if wanted is None else wanted
        if not self.self_collision:
            return None
        if not arm:
            raise ValueError(f"self_collision=True needs safety_spheres='arm' (its pairs are "
                             f"chosen for those spheres). Got: safety_spheres={spec!r}")
        m = self.model
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)
        base = m.body("panda0_link0").id
        offsets = np.array([s.offset for s in PANDA_BASE_SPHERES])
        fixed = d.xpos[base] + offsets @ d.xmat[base].reshape(3, 3).T
        return SelfCollisionPairs.of(PANDA_SELF_COLLISION_SPHERES, fixed_centres=fixed)

    @property
    def n_obstacle_barriers(self) -> int:
        """The (sphere, obstacle) barriers come first; the self-collision barriers
        (:attr:`n_self_collision_barriers`) and the joint-limit barriers follow."""
        return self._n_pairs

    @property
    def n_self_collision_barriers(self) -> int:
        """The self-collision barriers, after the obstacle ones (0 without
        ``self_collision``)."""
        return 0 if self._self_pairs is None else len(self._self_pairs)

    @property
    def _n_pair_barriers(self) -> int:
        """The barriers of sphere pairs (obstacle and self-collision), all of relative
        degree 2 with one learner each, before the joint-limit barriers."""
        return self._n_pairs + self.n_self_collision_barriers

    @property
    def barrier_layout(self) -> BarrierLayout:
        """Relative degree 2 for the obstacle and self-collision barriers, one learner each;
        the joint-limit barriers (2 for ranges, 1 for speeds) share one learner per joint,
        with their own hyperparameter group (:mod:`afvsgp_gym.envs.joint_limits`)."""
        return arm_layout(self._n_pair_barriers,
                          self.joint_limits if self.limit_barriers else None)

    @property
    def shared_barrier_layout(self) -> BarrierLayout:
        """:attr:`barrier_layout` with every obstacle pair projected onto the joint-limit
        barriers' seven learners (``learner = -1``; ``learner="afvsgp-shared"``, issue 45):
        a pair's model error is ``Delta h'' = n' J_s(q) Delta q''`` when the kinematics are
        known, so the terms carry ``projection`` = ``n' J_s`` (m/rad) per pair (a
        self-collision pair likewise, ``n'(J_a - J_b)``) and the seven
        joint-acceleration learners (each fed by its joint's range and speed barriers) predict
        every pair's band. Needs the joint-limit barriers and a nominal model that knows the
        kinematics (not ``"zero"``, whose terms hold no kinematics to project through)."""
        if self.nominal_model == "zero":
            raise ValueError("the shared learner needs the kinematics, which "
                             "nominal_model='zero' does not know: use 'kinematic' or "
                             "'perturbed', or the per-barrier learner 'afvsgp'")
        return arm_layout(self._n_pair_barriers,
                          self.joint_limits if self.limit_barriers else None, projected=True)

    def suggested_learner(self) -> str:
        """The learner ``SafetyFilter(learner="auto")`` (its default) runs: the shared one,
        ``"afvsgp-shared"``, where the nominal model knows the dynamics (``"perturbed"``, the
        robot's own model, or ``"exact"``), the joint-limit barriers are on and there are more
        than :attr:`SHARED_LEARNER_PAIRS` sphere pairs; the per-barrier ``"afvsgp"`` otherwise.
        With the robot's model as the prior the shared learner was as safe as the per-pair
        learners and tracked as well, and its step stays flat as pairs are added where theirs
        grows; with nothing of the dynamics known (``"kinematic"``) it tracked worse, and
        ``"zero"`` has no kinematics to project through (the docs' Safety and Performance
        pages have the figures)."""
        if (self.nominal_model in ("perturbed", "exact") and self.limit_barriers
                and self._n_pair_barriers > self.SHARED_LEARNER_PAIRS):
            return "afvsgp-shared"
        return "afvsgp"

    @property
    def activation_distance(self) -> float | np.ndarray:
        """Suggested activation distance: one per barrier (m for the obstacle and
        self-collision barriers, rad and rad/s for the joint-limit ones), or
        ``OBSTACLE_ACTIVATION`` without limits."""
        if not self.limit_barriers:
            return self.OBSTACLE_ACTIVATION
        n = self.joint_limits.n_joints
        return np.concatenate([np.full(self._n_pair_barriers, self.OBSTACLE_ACTIVATION),
                               np.full(2 * n, self.RANGE_ACTIVATION),
                               np.full(2 * n, self.SPEED_ACTIVATION)])

    @property
    def first_gain(self) -> np.ndarray:
        """Suggested first class-K gain per barrier: ``SPEED_GAIN`` for the joint speed
        barriers, NaN (the filter's ``alpha``) for the others."""
        parts = [np.full(self._n_pair_barriers, np.nan)]
        if self.limit_barriers:
            n = self.joint_limits.n_joints
            parts += [np.full(2 * n, np.nan), np.full(2 * n, self.SPEED_GAIN)]
        return np.concatenate(parts)

    @property
    def filter_defaults(self) -> dict[str, Any]:
        """The :class:`~afvsgp_gym.cbf.FilterConfig` options this env suggests to
        ``SafetyFilter`` (under the caller's): per-barrier activation distances, braking
        decelerations and first gains, the warm-up exploration, and with the joint-limit
        barriers the online correction of those barriers' band only
        (:func:`~afvsgp_gym.envs.joint_limits.limit_calibration`; not with ``beta = 0``, which
        has no band)."""
        out = {"activation_distance": self.activation_distance,
               "braking_deceleration": self.braking_deceleration,
               "first_gain": self.first_gain, **self.WARMUP_FILTER_DEFAULTS}
        if self.limit_barriers:
            out.update(limit_calibration(self._n_pair_barriers, self.joint_limits.n_joints))
        return out

    @property
    def braking_deceleration(self) -> np.ndarray:
        """Suggested braking deceleration per barrier (m/s^2 obstacles and self-collision
        pairs, rad/s^2 joint ranges, inf for the speed barriers of relative degree 1)."""
        parts = [np.full(self._n_pair_barriers, self.OBSTACLE_DECELERATION)]
        if self.limit_barriers:
            n = self.joint_limits.n_joints
            parts += [np.repeat(self.RANGE_DECELERATION, 2), np.full(2 * n, np.inf)]
        return np.concatenate(parts)

    @property
    def learner_defaults(self) -> dict[str, dict[str, Any]]:
        """Suggested learner settings by learner name (``learner_kwargs`` under the user's):
        a copy of ``ARM_LEARNER_DEFAULTS`` with several safety spheres, none with one."""
        if len(self.safety_spheres) < 2:
            return {}
        return {k: dict(v) for k, v in self.ARM_LEARNER_DEFAULTS.items()}

    def _catalogue_inertia(self, state: mujoco.MjData) -> np.ndarray:
        """``M_cat(q)`` (7, 7) of the catalogue model at the joint angles of ``state`` (the
        model is built on first use)."""
        if self._brake_model is None:
            model = fm.build_model(fm.PlantParameters(armature=self.plant.armature), self._scene)
            self._brake_model = (model, mujoco.MjData(model))
        m, d = self._brake_model
        d.qpos[:] = state.qpos
        mujoco.mj_fwdPosition(m, d)
        inv = np.empty((m.nv, m.nv))
        mujoco.mj_solveM(m, d, inv, np.eye(m.nv))
        return np.linalg.inv(inv)[:7, :7]

    def _catalogue_coriolis(self, state: mujoco.MjData) -> np.ndarray:
        """``C_cat(q, q') q'`` (7,) of the catalogue model at ``state``: its bias forces at
        the joint speeds minus those at rest (gravity cancels)."""
        self._catalogue_inertia(state)  # the model, built on first use
        m, d = self._brake_model
        d.qpos[:] = state.qpos
        out = np.empty(m.nv)
        rest = np.empty(m.nv)
        d.qvel[:] = 0.0
        mujoco.mj_fwdPosition(m, d)
        mujoco.mj_comVel(m, d)
        mujoco.mj_rne(m, d, 0, rest)
        d.qvel[:] = state.qvel
        mujoco.mj_comVel(m, d)
        mujoco.mj_rne(m, d, 0, out)
        return (out - rest)[:7]

    def _plant_parameters(self, scale, plant_seed, payload_mass: float, damping: float,
                          friction: float, armature: float) -> fm.PlantParameters:
        if np.ndim(scale) == 0:
            factors = np.full(9, float(scale))
        else:
            try:
                lo, hi = (float(x) for x in scale)
            except (TypeError, ValueError):
                raise ValueError(
                    f"mass_scale must be a float > 0 or (low, high), got {scale}"
                ) from None
            if not (0 < lo <= hi):
                raise ValueError(f"mass_scale must be a float > 0 or (low, high), got {scale}")
            factors = np.random.default_rng(int(plant_seed)).uniform(lo, hi, 9)
            factors[8] = factors[7]  # the two fingers alike
        if not np.all(factors > 0):
            raise ValueError(f"mass_scale must be > 0, got {scale}")
        return fm.PlantParameters(
            mass_scale=factors,
            payload_mass=float(payload_mass),
            damping=np.full(7, float(damping)),
            frictionloss=np.full(7, float(friction)),
            armature=np.full(7, float(armature)),
        )

    def _initialize_simulation(self):
        model = fm.build_model(self.plant, self._scene)
        model.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
        return model, mujoco.MjData(model)

    def _build_scenario(self, rng: np.random.Generator | None) -> None:
        c = self.reference_center
        ex, ey, ez = np.eye(3)
        t_w = self.warmup_steps * self._control_dt
        kind, switch = self.scenario, self._switch_time_arg
        radius, along, dz, dx = 0.05, 0.20, -0.07, 0.0
        start_off = None
        if kind == "dynamic":
            along = 0.15
            start_off = 0.5 * ex
        if kind == "random" and rng is not None:
            kind = "static" if rng.random() < 0.5 else "dynamic"
            radius = float(rng.uniform(0.04, 0.07))
            along = float(rng.uniform(radius + 0.15, max(radius + 0.15, 0.24)))
            along *= 1.0 if rng.random() < 0.5 else -1.0
            dz = float(rng.uniform(-0.09, -0.06))
            dx = float(rng.uniform(-0.02, 0.02))
            dist = float(rng.uniform(0.3, 0.5))
            if rng.random() < 0.5:
                start_off = dist * ex
            else:
                start_off = dist * np.sign(along) * ey
            speed = float(rng.uniform(0.05, 0.2))
            if switch is None and rng.random() < 0.5:
                switch = float(rng.uniform(t_w + 4.0, t_w + 8.0))
        elif kind == "random":
            kind = "static"
        else:
            speed = self.obstacle_speed
        if switch is None:
            switch = 10.0 if self.scenario == "static" else np.inf
        centre = c + along * ey + dz * ez + dx * ex
        center, axis1, amplitude = c.copy(), ey, self.AMPLITUDE
        if kind == "tabletop":
            obstacles = scenes.draw_tabletop(
                np.random.default_rng(0) if rng is None else rng, c, t_w)
        elif kind == "shelf":
            obstacles = scenes.shelf_obstacles(c)
            center = c + scenes.SHELF_REFERENCE["offset"]
            axis1, amplitude = ex, scenes.SHELF_REFERENCE["amplitude"]
        elif kind == "static":
            obstacles = [ObstacleSpec(centre, radius)]
        else:
            obstacles = [ObstacleSpec(centre, radius, centre + start_off, t_w, speed)]
        # a fresh tuple per scenario: _obstacle_constants is keyed on its identity
        self.obstacles = tuple(obstacles if self._user_obstacles is None else self._user_obstacles)
        if self._user_obstacles is None and self.scenario == "random":
            # visual sphere follows the drawn radius
            self.model.geom_size[self._obstacle_geoms[0], 0] = radius
        if self._user_obstacles is None and self.scenario == "tabletop":
            self._resize_geoms()
        self.reference = CyclicReference(
            center=center,
            axis1=axis1,
            axis2=ez,
            amplitude=amplitude,
            warmup_amplitude=self.WARMUP_AMPLITUDE,
            period=self.PERIOD,
            ramp_start=t_w,
            ramp_duration=1.0,
            switch_time=switch,
        )
        self._obstacle_radii = np.array([ob.radius for ob in self.obstacles])
        self._yielding = any(ob.yield_distance is not None for ob in self.obstacles)

    def _scene_layout(self) -> list[ObstacleSpec] | None:
        """The obstacles the tabletop's and the shelf's geoms are built from (None for the
        other scenarios, whose one obstacle is a sphere)."""
        c = scenes.READY_CENTER  # the sizes and kinds matter here, not the places
        t_w = self.warmup_steps * self._control_dt
        if self.scenario == "tabletop":
            return scenes.tabletop_template(c, t_w)
        if self.scenario == "shelf":
            return scenes.shelf_obstacles(c)
        return None

    def _resize_geoms(self) -> None:
        """Fit the obstacle geoms (built at the largest sizes) to a drawn scene: sizes,
        orientations in their bodies and bounding radii."""
        m = self.model
        for g, ob in zip(self._obstacle_geoms, self.obstacles, strict=True):
            geom = fm.obstacle_geom(ob)
            if geom is None:
                m.geom_size[g, 0] = ob.radius
                m.geom_rbound[g] = ob.radius
            elif geom.kind != "plane":
                m.geom_size[g] = geom.size
                m.geom_quat[g] = geom.quat
                m.geom_rbound[g] = ob.radius

    # ------------------------------------------------------------------ state
    @property
    def dt(self) -> float:
        """Control period (s): physics_dt * frame_skip."""
        return self._control_dt

    @property
    def time(self) -> float:
        return self._steps * self._control_dt

    def set_state(self, qpos, qvel) -> None:
        """Set joint positions/velocities (copies) and recompute everything derived."""
        super().set_state(qpos, qvel)
        self._after_state_change()

    def set_time_step(self, steps: int) -> None:
        """Jump the scenario clock to ``steps`` control periods (tests, plotting)."""
        self._steps = int(steps)
        self._after_state_change()

    def _after_state_change(self) -> None:
        d = self.data
        d.ctrl[:] = 0.0
        self._place_markers()
        mujoco.mj_forward(self.model, d)
        self._spheres, self._ee = self._kinematics(d)
        self_pairs = self._self_geometry(self._spheres)
        self._geometry = self._state_geometry(d, self._spheres, self._obstacle_states,
                                              self_pairs)
        if self._yielding:
            self._yield_obstacles(self._geometry[0])
        self._true_view = StateView(d, self._spheres, self._ee, self._geometry,
                                    self._obstacle_states, self_pairs)
        self._sensed_view = self._true_view if self.perception.exact else self._sense()
        self._invalidate_barriers()

    def _self_geometry(self, spheres) -> SelfPairGeometry | None:
        """The self-collision pairs' geometry at the sphere kinematics ``spheres`` (None
        without ``self_collision``)."""
        pairs = self._self_pairs
        return None if pairs is None else pairs.geometry(spheres[0], spheres[1])

    def _state_geometry(self, d: mujoco.MjData, spheres, states,
                        self_pairs: SelfPairGeometry | None = None) -> tuple[np.ndarray, ...]:
        """``(derivs, n, curv, xi, a_obs)`` of every barrier at joint state ``d``, sphere
        kinematics ``spheres``, obstacle states ``states`` and self-collision geometry
        ``self_pairs`` (``n``, ``curv`` and ``a_obs`` are the obstacle pairs' only)."""
        geometry = self._geometry_of(d, spheres, states)
        if self_pairs is not None:
            geometry = self._with_self_geometry(geometry, d, self_pairs)
        return self._with_limit_geometry(geometry, d) if self.limit_barriers else geometry

    def _with_self_geometry(self, geometry: tuple[np.ndarray, ...], d: mujoco.MjData,
                            self_pairs: SelfPairGeometry) -> tuple[np.ndarray, ...]:
        """``geometry`` with the self-collision pairs' ``[h, h']`` and features appended."""
        derivs, n, curv, xi, a_obs = geometry
        derivs = np.concatenate([derivs, np.column_stack([self_pairs.h, self_pairs.hd])])
        xi = np.concatenate([xi, self._self_pairs.features(self_pairs, d.qpos[:7],
                                                           d.qvel[:7], self.feature_dim)])
        derivs.flags.writeable = xi.flags.writeable = False
        return derivs, n, curv, xi, a_obs

    def _with_limit_geometry(self, geometry: tuple[np.ndarray, ...],
                             d: mujoco.MjData) -> tuple[np.ndarray, ...]:
        """The pairs' ``(derivs, n, curv, xi, a_obs)`` with the joint-limit barriers'
        derivatives and features appended (``n``, ``curv``, ``a_obs`` stay the obstacle
        pairs')."""
        derivs, n, curv, xi, a_obs = geometry
        lim, q, qd = self.joint_limits, d.qpos[:7], d.qvel[:7]
        derivs = np.concatenate([derivs, lim.derivatives(q, qd)])
        xi = np.concatenate([xi, lim.features(q, qd, self.feature_dim)])
        derivs.flags.writeable = xi.flags.writeable = False
        return derivs, n, curv, xi, a_obs

    def _yield_obstacles(self, derivs: np.ndarray) -> None:
        """Stop every yielding obstacle (``ObstacleSpec.yield_distance``) that a safety
        sphere has come within its distance of, from now on (its motion up to now, and so
        this step's obstacle states, unchanged; a new ``obstacles`` tuple)."""
        t, n_s = self.time, len(self._sphere_radii)
        out = list(self.obstacles)
        for o, ob in enumerate(out):
            near = ob.yields_at(t) and derivs[o * n_s:(o + 1) * n_s, 0].min() < ob.yield_distance
            if near:
                out[o] = ob.stopped_at(t)
        if any(a is not b for a, b in zip(out, self.obstacles, strict=True)):
            self.obstacles = tuple(out)
        # none left that can yield (stopped, or past its move): no more checks this episode
        self._yielding = any(ob.yield_distance is not None and ob.stop_time == math.inf
                             and t < ob.start_time + ob.duration for ob in self.obstacles)

    def _place_markers(self) -> None:
        t = self.time
        self._obstacle_states = [ob.state(t) for ob in self.obstacles]
        for k, (p, _, _) in zip(self._obstacle_mocap, self._obstacle_states, strict=True):
            self.data.mocap_pos[k] = p
        self._ref_state = self.reference.state(t)
        self.data.mocap_pos[self._ref_mocap] = self._ref_state[0]

    # ------------------------------------------------------------------ sensing
    def _setup_sensing(self) -> None:
        """The sensors and pushes of ``self.perception`` (:mod:`afvsgp_gym.envs.perception`;
        none when it is exact)."""
        per, m = self.perception, self.model
        self._camera = (ObstacleCamera(per, self._control_dt, self.n_obstacles)
                        if per.camera else None)
        self._encoders = JointEncoders(per) if per.encoders else None
        self._sensed_data = mujoco.MjData(m) if per.encoders else None
        self._estimate: tuple[int, list, np.ndarray | None] | None = None
        self._pushes = None
        if per.pushes:  # a point on the surface of one of the link's arm spheres
            bodies, offsets, radii = sphere_arrays(PANDA_ARM_SPHERES)
            ids = sorted({m.body(b).id for b in bodies})
            points = [np.array([[*off, r] for b, off, r in zip(bodies, offsets, radii,
                                                                strict=True)
                                if m.body(b).id == i]) for i in ids]
            self._pushes = Pushes(per, self._control_dt, np.array(ids), points)

    def _reseed_sensing(self) -> None:
        """New noise and pushes for the episode, from the env's seeded generator (drawn only
        when something is sensed or pushed, so exact envs keep their random streams)."""
        seed = int(self.np_random.integers(1 << 62))
        for part in (self._camera, self._encoders, self._pushes):
            if part is not None:
                part.reseed(seed)
        self._estimate = None
        self.data.xfrc_applied[:] = 0.0

    def _sense(self) -> StateView:
        """The state as the sensors give it: noisy encoders, and the obstacles from the
        estimate set for this control period (:meth:`set_obstacle_estimate`) or else the
        camera's raw reading."""
        d = self.data
        if self._sensed_data is not None:
            ds = self._sensed_data
            ds.qpos[:] = d.qpos
            ds.qvel[:] = d.qvel
            ds.qpos[:7], ds.qvel[:7] = self._encoders.measure(d.qpos[:7], d.qvel[:7])
            ds.mocap_pos[:] = d.mocap_pos
            ds.ctrl[:] = 0.0
            mujoco.mj_forward(self.model, ds)
            spheres, ee = self._kinematics(ds)
            self_pairs = self._self_geometry(spheres)
        else:
            ds, spheres, ee = d, self._spheres, self._ee
            self_pairs = self._true_view.self_pairs
        states = self._obstacle_states
        if self._camera is not None:
            est = self._estimate
            states = (est[1] if est is not None and est[0] == self._steps
                      else self._camera.raw_states(self.time, self.obstacles))
        if ds is d and states is self._obstacle_states:
            return self._true_view
        return StateView(ds, spheres, ee, self._state_geometry(ds, spheres, states, self_pairs),
                         states, self_pairs)

    def obstacle_reading(self) -> tuple[np.ndarray, float]:
        """The camera's newest sample of the obstacle centres (O, 3) and its sample time
        (s); without a camera the true centres now."""
        if self._camera is None:
            return np.array([st[0] for st in self._obstacle_states]), self.time
        pos, t = self._camera.reading(self.time, self.obstacles)
        return pos.copy(), t

    def set_obstacle_estimate(self, position: np.ndarray, velocity: np.ndarray,
                              acceleration: np.ndarray,
                              covariance: np.ndarray | None = None) -> None:
        """Use an estimate of the obstacles for this control period's sensed terms (instead
        of the camera's raw reading): ``position``, ``velocity``, ``acceleration`` (O, 3) and
        the per-axis covariance (O, 3, 3) of ``[p, v, a]`` (None: taken as exact). The terms'
        ``covariance`` then carries it (:func:`~afvsgp_gym.envs.perception.pair_covariance`)."""
        o = self.n_obstacles
        if covariance is not None and any(ob.shape is not None for ob in self.obstacles):
            raise ValueError("covariance: the estimate's covariance is propagated for sphere "
                             "obstacles only (pair_covariance); pass None with a box, capsule "
                             "or plane obstacle")
        arrays = [np.asarray(x, dtype=np.float64) for x in (position, velocity, acceleration)]
        for name, arr in zip(("position", "velocity", "acceleration"), arrays, strict=True):
            if arr.shape != (o, 3) or not np.isfinite(arr).all():
                raise ValueError(f"{name} must be a finite array of shape ({o}, 3). "
                                 f"Got shape {arr.shape}")
        if covariance is not None:
            covariance = np.asarray(covariance, dtype=np.float64)
            if covariance.shape != (o, 3, 3) or not np.isfinite(covariance).all():
                raise ValueError(f"covariance must be a finite array of shape ({o}, 3, 3) or "
                                 f"None. Got shape {covariance.shape}")
        states = [(arrays[0][i], arrays[1][i], arrays[2][i]) for i in range(o)]
        self._estimate = (self._steps, states, covariance)
        view = self._sensed_view  # the same joint reading: only the obstacles change
        self._sensed_view = StateView(view.data, view.spheres, view.ee,
                                      self._state_geometry(view.data, view.spheres, states,
                                                           view.self_pairs),
                                      states, view.self_pairs)
        self._invalidate_barriers()

    def _sensed_covariance(self, view: StateView, sphere_acc: np.ndarray | None
                           ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Covariance (K, 3, 3) of every barrier's ``[h, h', lf]`` as sensed, for a model
        whose ``lf`` holds the spheres' accelerations ``sphere_acc`` (S, 3; None: ``lf = 0``):
        the obstacle estimate's (when one with a covariance is set;
        :func:`~afvsgp_gym.envs.perception.pair_covariance`) and the encoders' noise (to first
        order: ``n' J_s`` times the joint noise for the pairs, ``n'(J_a - J_b)`` for the
        self-collision pairs, which the obstacle estimate does not touch; ``q``, ``q'``
        directly for the joint limits); None when neither is known. And the mean of ``lf``'s
        error (K,) to second order, which ``lf`` loses (None: none): the curvature ``|P v|^2
        / |d|`` is convex in the obstacle's velocity, so its estimate is high by ``tr(P
        Sigma_v) / |d| = 2 sigma_v^2 / |d|`` on average."""
        est = self._estimate
        obstacle_cov = est[2] if est is not None and est[0] == self._steps else None
        enc = self._encoders
        if obstacle_cov is None and enc is None:
            return None, None
        derivs, n, _, xi, _ = view.geometry
        k = len(n)
        cov = np.zeros((len(derivs), 3, 3))
        bias = None
        if obstacle_cov is not None and k:
            n_s = len(view.spheres[0])
            per_pair = np.repeat(obstacle_cov, n_s, axis=0)
            dist = np.linalg.norm(xi[:k, 14:17], axis=1)
            w = None
            if sphere_acc is not None:
                a_o = np.repeat(np.array([st[2] for st in view.obstacle_states]), n_s, axis=0)
                w = np.tile(sphere_acc, (self.n_obstacles, 1)) - a_o
            cov[:k] = pair_covariance(n, dist, xi[:k, 17:20], per_pair, w)
            if sphere_acc is not None:
                bias = np.zeros(len(derivs))
                bias[:k] = 2.0 * per_pair[:, 1, 1] / dist
        if enc is not None:
            sq, sv = enc.position_noise ** 2, enc.velocity_noise ** 2
            if k:
                jac = view.spheres[2]
                rows = np.einsum("ki,kij->kj", n, jac[np.arange(k) % len(jac)][:, :, :7])
                gain = np.einsum("kj,kj->k", rows, rows)
                cov[:k, 0, 0] += sq * gain
                cov[:k, 1, 1] += sv * gain
            pairs = view.self_pairs
            if pairs is not None:
                rows = self._self_pairs.rows(pairs, view.spheres[2])[:, :7]
                gain = np.einsum("kj,kj->k", rows, rows)
                cov[k : k + len(gain), 0, 0] += sq * gain
                cov[k : k + len(gain), 1, 1] += sv * gain
            if self.limit_barriers:
                j, s = self.joint_limits.n_joints, self._n_pair_barriers
                cov[s : s + 2 * j, 0, 0] += sq
                cov[s : s + 2 * j, 1, 1] += sv
                cov[s + 2 * j :, 0, 0] += sv
        cov.flags.writeable = False
        return cov, bias

    def sensing_errors(self) -> dict[str, float]:
        """The sensed state's errors: the largest obstacle centre error (m) and joint
        errors (rad, rad/s), 0.0 where sensed exactly."""
        true, sensed = self._true_view, self._sensed_view
        if sensed is true:
            return {"obstacle_error": 0.0, "joint_position_error": 0.0,
                    "joint_velocity_error": 0.0}
        err = max((float(np.linalg.norm(np.asarray(a[0]) - b[0]))
                   for a, b in zip(sensed.obstacle_states, true.obstacle_states, strict=True)),
                  default=0.0)
        return {"obstacle_error": err,
                "joint_position_error": float(np.abs(sensed.data.qpos[:7]
                                                     - true.data.qpos[:7]).max()),
                "joint_velocity_error": float(np.abs(sensed.data.qvel[:7]
                                                     - true.data.qvel[:7]).max())}

    # ------------------------------------------------------------------ barriers
    def _sphere_centres(self, data: mujoco.MjData) -> np.ndarray:
        """(S, 3) safety-sphere centres at the kinematics of ``data``."""
        body = self._sphere_body_ids
        p = np.matmul(data.xmat[body].reshape(-1, 3, 3), self._sphere_offset_cols).reshape(-1, 3)
        p += data.xpos[body]
        return p

    def _point_kinematics(self, d: mujoco.MjData
                          ) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, np.ndarray]]:
        """Safety spheres ``(p (S, 3), v (S, 3), J (S, 3, nv), J' q' (S, 3))`` from MuJoCo's
        point Jacobian and its time derivative at each centre (``mj_jac``, ``mj_jacDot``),
        and the end-effector site's ``(p, v)``, at the state of ``d``. The Jacobians share
        one fresh buffer (``_ee_jac`` is its last block), so one product with ``q'`` gives
        every velocity."""
        m = self.model
        p = self._sphere_centres(d)
        n_s = p.shape[0]
        jac = np.empty((2 * n_s + 1, 3, m.nv))  # [J_s ..., J_s' ..., J_ee]
        for i, b in enumerate(self._sphere_bodies):
            mujoco.mj_jac(m, d, jac[i], None, p[i], b)
            mujoco.mj_jacDot(m, d, jac[n_s + i], None, p[i], b)
        self._ee_jac = jac[-1]
        mujoco.mj_jacSite(m, d, self._ee_jac, None, self._site)
        vel = jac @ d.qvel
        spheres = (p, vel[:n_s], jac[:n_s], vel[n_s : 2 * n_s])
        return spheres, (d.site_xpos[self._site].copy(), vel[-1])

    def _site_kinematics(self, d: mujoco.MjData
                         ) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, np.ndarray]]:
        """:meth:`_point_kinematics` when the one sphere is the end-effector site: its
        Jacobian is the site's (``mj_jacSite`` is ``mj_jac`` at ``site_xpos``)."""
        m = self.model
        p = d.site_xpos[self._site].copy()
        jac = np.empty((2, 3, m.nv))  # [J_s, J_s']: numpy multiplies block by block, so the
        # velocities are those of the general path's stack
        self._ee_jac = jac[0]
        mujoco.mj_jacSite(m, d, self._ee_jac, None, self._site)
        mujoco.mj_jacDot(m, d, jac[1], None, p, self._sphere_bodies[0])
        vel = jac @ d.qvel
        return (p[None], vel[:1], jac[:1], vel[1:]), (p, vel[0])

    def _obstacle_constants(self) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """What stays fixed while ``self.obstacles`` is the same tuple (rebuilt when a new one
        is set): the pair radii ``r_o + r_s`` (O S,), the stacked states (O, 3, 3) of
        obstacles that are all static (else None) and the squared contact reach of the arm
        geoms (O, G; a bounding ball's for a box or capsule, inf for a plane). Beside them
        ``_shape_const``: when some obstacle is not a sphere, ``(ShapeStack, sphere radius per
        pair (O S,), mask of the sphere obstacles' pairs (O S,))`` for
        :func:`~afvsgp_gym.envs.primitives.pair_barriers`, else None."""
        key = self.obstacles
        if self._obstacle_key is not key:
            radii = self._obstacle_radii
            rad = (radii[:, None] + self._sphere_radii[None, :]).ravel()
            static = None
            if all(ob.duration == 0.0 for ob in key):
                static = np.array([ob.state(0.0) for ob in key])
            reach = self._arm_rbound[None, :] + np.array([ob.radius for ob in key])[:, None]
            shapes = None
            if any(ob.shape is not None for ob in key):
                n_s = len(self._sphere_radii)
                shapes = (stack_shapes([ob.primitive for ob in key], n_s),
                          np.tile(self._sphere_radii, len(key)),
                          np.repeat([ob.shape is None for ob in key], n_s))
            self._obstacle_const = (rad, static, reach * reach)
            self._shape_const = shapes
            self._obstacle_key = key
        return self._obstacle_const

    def _pair_geometry(self, data: mujoco.MjData, spheres,
                       states) -> tuple[np.ndarray, ...]:
        """Kinematic part of every (sphere, obstacle) barrier, shared by all models:
        ``[h, h']`` (K, 2), ``n``, curvature, features ``xi`` (K, 20) and the obstacle
        accelerations per pair (None when every obstacle is static and seen exactly)."""
        p, v, _, _ = spheres
        rad, static, _ = self._obstacle_constants()
        shapes = self._shape_const
        if states is not self._obstacle_states:
            static = None  # measured: not the scenario's constants
        st = np.array(states) if static is None else static
        n_s = p.shape[0]
        d = (p[None, :, :] - st[:, None, 0, :]).reshape(-1, 3)
        vr = (v[None, :, :] - st[:, None, 1, :]).reshape(-1, 3)
        if shapes is None:  # spheres only: today's arithmetic
            h, hd, n, curv = sphere_barriers(d, vr, rad)
            offset = d
        else:  # closest-feature geometry; the offset from the closest surface point
            stack, sphere_rad, sphere_rows = shapes
            h, hd, n, curv = pair_barriers(stack, d, vr, sphere_rad)
            offset = np.where(sphere_rows[:, None], d, n * (h + sphere_rad)[:, None])
        k = len(h)
        derivs = np.empty((k, 2))
        derivs[:, 0] = h
        derivs[:, 1] = hd
        xi = np.empty((k, 20))
        xi[:, :7] = data.qpos
        xi[:, 7:14] = data.qvel
        xi[:, 14:17] = offset
        xi[:, 17:] = vr
        derivs.flags.writeable = xi.flags.writeable = False
        a_obs = None if static is not None else np.repeat(st[:, 2], n_s, axis=0)
        return derivs, n, curv, xi, a_obs

    def _one_pair_geometry(self, data: mujoco.MjData, spheres,
                           states) -> tuple[np.ndarray, ...]:
        """:meth:`_pair_geometry` for one sphere and one obstacle, in Python floats."""
        p, v, _, _ = spheres
        po, vo, ao = states[0]
        d, vr = (p[0] - po).tolist(), (v[0] - vo).tolist()
        h, hd, n, curv = sphere_barrier(d, vr, float(self._obstacle_constants()[0][0]))
        derivs = np.array([[h, hd]])
        xi = np.array([data.qpos.tolist() + data.qvel.tolist() + d + vr])
        derivs.flags.writeable = xi.flags.writeable = False
        exact_static = self.obstacles[0].duration == 0.0 and states is self._obstacle_states
        a_obs = None if exact_static else np.asarray(ao, dtype=np.float64)[None]
        return derivs, np.array([n]), np.array([curv]), xi, a_obs

    def _zero_terms(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Read-only ``lf = 0`` (k,) and ``lg = 0`` (k, 7), made once."""
        zero = self._zeros
        if zero is None or len(zero[0]) != k:
            zero = self._zeros = (np.zeros(k), np.zeros((k, 7)))
            for arr in zero:
                arr.flags.writeable = False
        return zero

    def _compute_barriers(self, kind: str, truth: bool = False) -> BarrierSet:
        return self._torque_terms(kind, truth)

    def _torque_terms(self, kind: str, truth: bool = False) -> BarrierSet:
        """The terms of model ``kind`` per unit of the joint-torque action (``action_scale``)
        at the sensed state (``truth``: the true one), computed once per state (subclasses
        with another action compose them)."""
        view = self._true_view if truth else self._sensed_view
        key = ("torque:" if view is self._true_view else "sensed:") + kind
        terms = self._barrier_cache.get(key)
        if terms is None:
            terms, sphere_acc = self._joint_torque_barriers(kind, view)
            if view is not self._true_view:
                cov, bias = self._sensed_covariance(view, sphere_acc)
                if bias is not None:
                    lf = terms.lf - bias
                    lf.flags.writeable = False
                    terms = replace(terms, lf=lf)
                terms = replace(terms, covariance=cov)
            self._barrier_cache[key] = terms
        return terms

    def true_state_terms(self, model: str = "true") -> BarrierSet:
        """The terms of ``model`` at the true state, as exact perception would give them
        (ground truth for evaluation: ``info["delta_b_true"]``; the filter never sees them).
        The same as :meth:`barrier_terms` when the env senses exactly."""
        if self._sensed_view is self._true_view:
            return self.barrier_terms(model)
        kind = {"true": "exact", "nominal": self.nominal_model}.get(model)
        if kind is None:
            check_choice("model", model, ("nominal", "true"))
        key = "truth:" + kind
        terms = self._barrier_cache.get(key)
        if terms is None:
            terms = self._barrier_cache[key] = self._compute_barriers(kind, truth=True)
        return terms

    def _joint_torque_barriers(self, kind: str,
                               view: StateView) -> tuple[BarrierSet, np.ndarray | None]:
        """The terms of model ``kind`` at ``view``, and the spheres' accelerations at zero
        action (S, 3) that their ``lf`` holds (None for the zero model)."""
        derivs, n, curv, xi, a_obs = view.geometry
        k = len(curv)  # obstacle pairs; the self-collision and joint-limit barriers follow
        if kind == "zero":
            return BarrierSet(derivs, *self._zero_terms(len(derivs)), xi), None
        _, _, jac, bias = view.spheres
        n_s = jac.shape[0]
        ns = n.reshape(-1, n_s, 3)  # (obstacles, spheres, 3)
        limits = None
        if kind == "kinematic":  # joint accelerations are dynamics: nothing known
            acc, gain, lg = bias, None, np.zeros((k, 7))
            if self.limit_barriers:
                limits = (np.zeros(self.joint_limits.n_barriers),
                          np.zeros((self.joint_limits.n_barriers, 7)))
        else:
            m, d = self.model, view.data
            if kind == "perturbed" and self.nominal_mj_data is not None:
                m, d = self.nominal_mj_model, self.nominal_mj_data
                d.qpos[:] = view.data.qpos
                d.qvel[:] = view.data.qvel
                d.ctrl[:] = 0.0
                mujoco.mj_forward(m, d)
            flat = jac.reshape(3 * n_s, -1)
            if self.limit_barriers:  # one solve for the sphere rows and M^-1 itself
                rhs = np.concatenate([flat, np.eye(m.nv)])
                sol = np.empty_like(rhs)
                mujoco.mj_solveM(m, d, sol, rhs)  # rows J M^-1 and M^-1 (M symmetric)
                jminv = sol[: 3 * n_s]
                limits = self.joint_limits.terms(d.qacc[:7], sol[3 * n_s :, :7]
                                                 * self.action_scale)
            else:
                jminv = np.empty_like(flat)
                mujoco.mj_solveM(m, d, jminv, flat)  # rows J M^-1 (M symmetric)
            acc = jac @ d.qacc + bias
            gain = jminv.reshape(n_s, 3, -1) * self.action_scale
            lg = np.einsum("osi,sij->osj", ns, gain).reshape(k, -1)
        if k == 1:  # one pair: the same sums in Python floats (dot3)
            n1 = n[0].tolist()
            lf1 = dot3(n1, acc[0].tolist())
            if a_obs is not None:
                lf1 -= dot3(n1, a_obs[0].tolist())
            lf = np.array([lf1 + float(curv[0])])
        else:
            lf = np.einsum("osi,si->os", ns, acc).ravel()
            if a_obs is not None:  # static obstacles: a_o = 0
                lf -= np.einsum("ki,ki->k", n, a_obs)
            lf += curv
        pairs = view.self_pairs
        if pairs is not None:
            lf_self, lg_self = self._self_pairs.terms(pairs, acc, gain, lg.shape[1])
            lf, lg = np.concatenate([lf, lf_self]), np.concatenate([lg, lg_self])
        projection = None
        if limits is not None:
            lf = np.concatenate([lf, limits[0]])
            lg = np.concatenate([lg, limits[1]])
            rows = np.einsum("osi,sij->osj", ns, jac).reshape(k, -1)
            if pairs is not None:
                rows = np.concatenate([rows, self._self_pairs.rows(pairs, jac)])
            projection = joint_projection(rows, self.joint_limits)
        lf.flags.writeable = lg.flags.writeable = False
        return BarrierSet(derivs, lf, lg, xi, projection=projection), acc

    def true_terms_error_bound(self) -> np.ndarray:
        """``(n_barriers,)`` bound on ``|h''_true(u) - (lf + lg u)|`` of the ``"true"`` terms
        over all actions: they take joint friction (frictionloss ``f_j``) at u = 0, and a
        torque changes joint j's friction force by at most ``2 f_j``, so the error is at most
        ``2 sum_j |n' J_s M^-1|_j f_j``; 0 without friction."""
        f = np.asarray(self.model.dof_frictionloss[:7], dtype=np.float64)
        if not f.any():
            return np.zeros(self.n_barriers)
        lg = self._torque_terms("exact").lg
        return 2.0 * (np.abs(lg) @ (f / self.action_scale))

    def backup_action(self) -> np.ndarray:
        """The robot's own brake for the safety filter's backup: stop every joint and hold it,
        ``tau = C_cat(q, q') q' + M_cat(q) (-2 w q' - w^2 (q - q_hold))`` as an action (``w`` =
        ``brake_frequency``, critically damped; ``C_cat`` the catalogue's Coriolis term), with
        ``q_hold`` the joint angles when the backup was first asked for in a run of control
        periods none more than ``brake_hold_memory`` apart. Beyond the torque limits it only
        damps, with the largest share ``s`` in [0, 1] of ``M_cat (-2 w q')`` that the limits
        admit: the commanded joint accelerations keep their direction, so every joint keeps
        decelerating. (Clipping each joint's torque apart bent it through the coupled
        inertia and drove joint 4 to 7 rad/s while braking, 3x its datasheet speed; a
        saturated spring back to where the brake engaged swung a 3 kg payload's wrist past
        its speed.) A saturated period takes the hold point anew where the arm is, unless
        every joint is within ``brake_hold_slack`` of it (0 by default): where the brake
        saturates every few periods, a hold point taken anew can ratchet the sag. (Before the
        give-way's hysteresis a hand sank 1.7 cm into the tabletop's table that way; 0.02 rad
        kept it clear, but gave another seed of the scene cost.)

        It gives way to moving obstacles (:meth:`_give_way_velocity`): the hold point then
        moves at that joint velocity and the brake tracks it, ``-2 w (q' - q'_give)``.

        ``M_cat`` is the catalogue inertia (the links unscaled, no payload, the plant's rotor
        inertia): the robot's own model, as its gravity compensation uses the catalogue
        masses, not the filter's (which may know nothing). Scaled by the inertia, the brake
        decelerates light and heavy configurations alike: a damping without it either
        chatters on the light, folded joints (a gain of tau_max per rad/s flips joint 1's
        speed every control period) or stops the heavy, stretched ones slowly. With the true
        inertia within a factor of ~2 of the catalogue's, ``w dt`` = 0.2 keeps the sampled
        loop well damped; the spring holds the arm against its uncompensated weight (a sag of
        ``residual torque / (M w^2)``, a few mrad). Far from rest it saturates: the torque
        limits brake, at the largest deceleration of that direction.

        The hold point outlives runs of feasible steps up to ``brake_hold_memory`` (0.1 s by
        default) while the obstacles stand still: where the chance program flips between
        feasible and infeasible every few periods, a hold point taken anew at each engagement
        starts from the sagged pose each time, and the sag ratchets (on the tabletop a hand
        sank 3 cm into the table in 1000 such periods). The arm was at the old hold point, so
        it is clear of obstacles that have not moved since; an obstacle that moved (more than
        ``HOLD_WORLD_TOLERANCE`` as the robot senses it) may now be where the arm left, and
        the brake then holds where the arm is (a spring back to a stale hold point drove a
        hand into a moving sphere). ``brake_hold_memory=0`` takes a fresh hold point at every
        engagement: with nothing known it had cost in 6 of the tabletop's and shelf's 137
        braking episodes where the kept hold point had none, and the nominal-only filter's
        braking episodes of the acceptance grid spent 2.3x the steps on the brake
        (``benchmarks/results/hold_memory.jsonl.gz``).
        """
        d = self._sensed_view.data  # the robot's own sensors
        world = (np.array([st[0] for st in self._sensed_view.obstacle_states])
                 if self._hold_memory_steps else None)  # compared only with a memory
        gap = self._steps - self._backup_step - 1
        if self._hold is None or (gap > 0 and (gap > self._hold_memory_steps
                                              or self._world_moved(world))):
            self._hold = d.qpos[:7].copy()
        self._backup_step, self._hold_world = self._steps, world
        w = self.brake_frequency
        inertia = self._catalogue_inertia(d)
        give_way = self._give_way_velocity()
        if give_way is not None:  # the hold point moves out of the obstacles' way
            lim = self.joint_limits  # (held inside the range barriers' margin)
            self._hold = np.clip(self._hold + give_way * self._control_dt,
                                 lim.lower + lim.range_margin, lim.upper - lim.range_margin)
        target = 0.0 if give_way is None else give_way
        acc = -(2.0 * w * (d.qvel[:7] - target) + w * w * (d.qpos[:7] - self._hold))
        brake = (inertia @ acc) / self._gear
        coriolis = self._catalogue_coriolis(d) / self._gear
        u = coriolis + brake
        if np.abs(u).max() > 1.0:  # saturated: damping only, and its largest share
            if np.abs(d.qpos[:7] - self._hold).max() > self.brake_hold_slack:
                self._hold = d.qpos[:7].copy()  # (a spring back from afar winds up)
            brake = (inertia @ (-2.0 * w * (d.qvel[:7] - target))) / self._gear
            share = admissible_share(coriolis, brake, 1.0)
            u = np.clip(coriolis + share * brake, -1.0, 1.0)
        return u * (1.0 if self.normalize_action else self._gear)

    def _world_moved(self, world: np.ndarray) -> bool:
        """Whether an obstacle centre ``world`` (O, 3) moved more than
        ``HOLD_WORLD_TOLERANCE`` since the brake's last period."""
        last = self._hold_world
        return (last is None or last.shape != world.shape
                or bool(np.abs(world - last).max(initial=0.0) > self.HOLD_WORLD_TOLERANCE))

    def _give_way_velocity(self) -> np.ndarray | None:
        """Joint velocity (7,) with which the brake gives way to moving obstacles, or None
        (every obstacle static, or none approaching within ``EVADE_DISTANCE``).

        A held arm is not safe from an obstacle that moves into it (``h' = n.(v_s - v_o)``
        with ``v_s = 0``). For each pair closer than ``EVADE_DISTANCE`` whose obstacle
        approaches the sphere (``n.v_o > 0``, ``n`` from the obstacle to the sphere; a pair
        given way within the hold memory until ``EVADE_HYSTERESIS`` beyond the distance) the
        sphere is asked to recede along ``n`` at ``EVADE_FACTOR n.v_o``: the least-norm
        joint velocity of those rows ``n' J_s`` (damped least squares) over the joints not
        held at their range margin (:meth:`_free_joint_velocity`), scaled into
        ``EVADE_SPEED_SHARE`` of the joint speed limits. Every other pair closer than
        ``EVADE_DISTANCE`` must not close in, ``h' = n' J_s q' - n.v_o >= 0``: a pair that
        would is held at ``h' = 0`` and the rows solved again, until none would (giving way
        to the forearm alone drove joint 2 at its give-way speed and a hand 32 cm into the
        table). Where the rows conflict, damped least squares weighs them. It is the
        robot's own reflex, with the kinematics and the obstacles' measured motion, not the
        filter's model. Called once per brake period: it records the pairs given way (the
        hysteresis' state, ``_giving_way``)."""
        view = self._sensed_view
        exact_static = (self._obstacle_constants()[1] is not None
                        and view.obstacle_states is self._obstacle_states)
        if exact_static or not self._n_pairs:
            return None
        k = self._n_pairs  # the pairs' h and n of this step (the limit rows follow them)
        h, n = view.geometry[0][:k, 0], view.geometry[1]
        jac, n_s = view.spheres[2], len(view.spheres[0])
        approach = (n * np.repeat(np.array([st[1] for st in view.obstacle_states]), n_s,
                                  axis=0)).sum(1)
        near = h < self.EVADE_DISTANCE
        last_step, last_rows = self._giving_way
        if (self._steps - last_step <= max(1, self._hold_memory_steps)
                and last_rows.shape == near.shape):
            near |= last_rows & (h < self.EVADE_DISTANCE + self.EVADE_HYSTERESIS)
        rows = np.flatnonzero(near & (approach > 0.0))
        given = np.zeros(len(h), dtype=bool)
        given[rows] = True
        self._giving_way = (self._steps, given)
        if not len(rows):
            return None
        others = np.flatnonzero(near & (approach <= 0.0))
        a = np.einsum("ki,kij->kj", n[rows], jac[rows % n_s][:, :, :7])
        b = self.EVADE_FACTOR * approach[rows]
        a_other = np.einsum("ki,kij->kj", n[others], jac[others % n_s][:, :, :7])
        held = np.zeros(len(others), dtype=bool)
        while True:
            qd = self._free_joint_velocity(np.vstack([a, a_other[held]]),
                                           np.concatenate([b, approach[others][held]]))
            if qd is None:
                return None
            closing = ~held & (a_other @ qd < approach[others] - 1e-9)
            if not closing.any():
                break
            held |= closing
        top = self.EVADE_SPEED_SHARE * self.joint_limits.max_speed
        scale = float(np.max(np.abs(qd) / top))
        return qd / scale if scale > 1.0 else qd

    def _free_joint_velocity(self, a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
        """The least-norm joint velocity with ``a qd = b`` (damped least squares) over the
        joints free to move that way: a joint whose hold point (or angle) would pass its
        range barriers' margin within one period is locked and the rest solved again (a
        hold point clipped at the margin left joint 4 still while the sphere struck the
        arm). None when every joint is locked."""
        lim, dt = self.joint_limits, self._control_dt
        q = self._hold if self._hold is not None else self._sensed_view.data.qpos[:7]
        low, high = lim.lower + lim.range_margin, lim.upper - lim.range_margin
        free = np.ones(len(q), dtype=bool)
        damping = 1e-4 * np.eye(len(b))
        while free.any():
            af = a[:, free]
            qd = np.zeros(len(q))
            qd[free] = af.T @ np.linalg.solve(af @ af.T + damping, b)
            ahead = q + qd * dt
            locked = free & (((ahead <= low) & (qd < 0.0)) | ((ahead >= high) & (qd > 0.0)))
            if not locked.any():
                return qd
            free &= ~locked
        return None

    # ------------------------------------------------------------------ gym API
    def _tracked_point(self) -> np.ndarray:
        return self._ee[0]

    def _get_obs(self) -> np.ndarray:
        view = self._sensed_view  # what the sensors give
        p, v = view.ee
        r, rd, rdd = self._ref_state
        obs = np.concatenate(
            [view.data.qpos, view.data.qvel, p, v]
            + [s[0] for s in view.obstacle_states]
            + [s[1] for s in view.obstacle_states]
            + [r, rd, rdd]
        )
        np.minimum(np.maximum(obs, self._obs_low, out=obs), self._obs_high, out=obs)  # clip
        return obs.astype(np.float32)

    def _contact(self) -> bool:
        m, d = self.model, self.data
        reach2 = self._obstacle_constants()[2]
        pos = d.geom_xpos[self._arm_geoms]
        for k, g_obs in enumerate(self._obstacle_geoms):
            diff = pos - self._obstacle_states[k][0]
            shape = self.obstacles[k].shape
            if isinstance(shape, Plane):  # the geoms' bounding spheres reaching the plane
                near = diff @ shape.normal < self._arm_rbound
            else:
                near = np.einsum("ij,ij->i", diff, diff) < reach2[k]
            if not near.any():
                continue
            for g in self._arm_geoms[near]:
                if mujoco.mj_geomDistance(m, d, int(g), int(g_obs), 0.01, None) < 0:
                    return True
        return False

    def reset_model(self) -> np.ndarray:
        self._steps = 0
        if self.scenario in ("random", "tabletop"):
            self._build_scenario(self.np_random)
        noise = self.np_random.uniform(-self.reset_noise, self.reset_noise, 7)
        self.data.qpos[:] = self.q_home + noise
        self.data.qvel[:] = 0.0
        self.data.warning.number[:] = 0
        self._step_rates = (None, None)
        self._last_torque = np.zeros(7)
        self._hold, self._backup_step, self._hold_world = None, -2, None
        self._giving_way = (-2, np.zeros(0, dtype=bool))
        if not self.perception.exact:
            self._reseed_sensing()
        self._after_state_change()
        return self._get_obs()

    def _get_reset_info(self) -> dict[str, Any]:
        return self._reset_info()

    def _safety_info(self) -> dict[str, Any]:
        """The base's (from the true state), whether the arm touches itself
        (:meth:`_self_contact`, counted as cost), the sensing errors
        (:meth:`sensing_errors`) and whether a push acts."""
        info = super()._safety_info()
        info["self_contact"] = self._self_contact()
        if info["self_contact"]:
            info["cost"] = 1.0
        info.update(self.sensing_errors())
        info["push_active"] = self._pushes is not None and self._pushes.body >= 0
        return info

    def _self_contact(self) -> bool:
        """Some two collision geoms of the robot (the arm's and the base's) on non-adjacent
        links touch (``mj_geomDistance`` < 0; the pairs of :func:`self_contact_geom_pairs`, those
        whose bounding spheres overlap)."""
        return self._self_contact_pairs.touching(self.model, self.data)

    def _limit_violation(self) -> bool:
        """A joint at its range stop or above its speed (or, with ``check_acceleration`` /
        ``check_torque_rate``, above those limits over the last step)."""
        d = self.data
        return self.joint_limits.violation(d.qpos[:7], d.qvel[:7], *self._step_rates)

    def _advance(self, u: np.ndarray) -> bool:
        m, d = self.model, self.data
        warn_before = int(d.warning.number[_BAD_WARNINGS].sum())
        lim = self.joint_limits
        if lim.max_acceleration is not None or lim.max_torque_rate is not None:
            torque = u * self.action_scale  # Nm on top of the gravity compensation
            qd_before = d.qvel[:7].copy()
        d.ctrl[:] = u * self._ctrl_per_action
        if self._pushes is not None:
            self._pushes.step(self.time)
            self._pushes.apply(d.xfrc_applied, d.xpos, d.xmat, d.xipos)
        mujoco.mj_step(m, d, nstep=self.frame_skip)
        if lim.max_acceleration is not None or lim.max_torque_rate is not None:
            dt = self._control_dt
            self._step_rates = ((d.qvel[:7] - qd_before) / dt,
                                (torque - self._last_torque) / dt)
            self._last_torque = torque
        self._steps += 1
        warn_after = int(d.warning.number[_BAD_WARNINGS].sum())
        unstable = warn_after > warn_before or not math.isfinite(float(d.qpos.sum() + d.qvel.sum()))
        if unstable:
            d.qpos[:] = np.nan_to_num(d.qpos)
            d.qvel[:] = 0.0
        self._after_state_change()
        return unstable


class _GeomPairs(NamedTuple):
    """Pairs ``(first[i], second[i])`` of geom ids with the squared sums of their bounding
    radii ``reach2``; ``first_xyz``, ``second_xyz`` index the flat ``geom_xpos``."""

    first: list[int]
    second: list[int]
    first_xyz: np.ndarray
    second_xyz: np.ndarray
    reach2: np.ndarray

    @classmethod
    def of(cls, first: np.ndarray, second: np.ndarray, rbound: np.ndarray) -> _GeomPairs:
        reach = rbound[first] + rbound[second]
        xyz = np.arange(3)
        return cls(first.tolist(), second.tolist(), (3 * first[:, None] + xyz).ravel(),
                   (3 * second[:, None] + xyz).ravel(), reach * reach)

    def near(self, geom_xpos: np.ndarray) -> list[tuple[int, int]]:
        """The pairs whose bounding spheres overlap at the geom positions ``geom_xpos``."""
        flat = geom_xpos.ravel()
        diff = (flat[self.first_xyz] - flat[self.second_xyz]).reshape(-1, 3)
        rows = np.flatnonzero(np.einsum("ij,ij->i", diff, diff) < self.reach2).tolist()
        return [(self.first[i], self.second[i]) for i in rows]

    def touching(self, m: mujoco.MjModel, d: mujoco.MjData) -> bool:
        """Some pair touches (``mj_geomDistance`` < 0) at ``d``'s geom poses (only the pairs
        whose bounding spheres overlap are asked)."""
        for a, b in self.near(d.geom_xpos):
            if mujoco.mj_geomDistance(m, d, a, b, 0.01, None) < 0:
                return True
        return False


def self_contact_geom_pairs(m: mujoco.MjModel) -> _GeomPairs:
    """The pairs of the Panda's collision geoms (the base's and the arm's: links 1-7, hand,
    fingers) on links at least two apart in the chain
    (:func:`~afvsgp_gym.envs.self_collision.chain_index`: a geom on link7 beyond the flange
    is the hand's) that do not touch at the ready pose: ``info["self_contact"]``'s pairs."""
    g = np.concatenate([fm.base_collision_geoms(m), fm.arm_collision_geoms(m)])
    index = np.array([chain_index(m.body(m.geom_bodyid[i]).name, m.geom_pos[i, 2])
                      for i in g])
    ia, ib = np.triu_indices(len(g), 1)
    far = np.abs(index[ia] - index[ib]) >= 2
    a, b = g[ia[far]], g[ib[far]]
    d = mujoco.MjData(m)
    d.qpos[:7] = fm.Q_HOME
    mujoco.mj_kinematics(m, d)
    apart = np.array([mujoco.mj_geomDistance(m, d, int(x), int(y), 0.01, None) >= 0.0
                      for x, y in zip(a, b, strict=True)], dtype=bool)
    return _GeomPairs.of(a[apart], b[apart], m.geom_rbound)


#: Half extent (m) of the rectangle drawn for a plane obstacle (:mod:`franka_model`'s).
PLANE_DRAW_HALF_EXTENT = fm.PLANE_DRAW_HALF_EXTENT
