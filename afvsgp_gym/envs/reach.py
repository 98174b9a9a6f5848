"""Franka Panda reaching a goal past spherical obstacles: the reinforcement-learning task."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from gymnasium import spaces

from afvsgp_gym.envs.base import NOMINAL_MODELS, keyword_defaults, named_arguments
from afvsgp_gym.envs.franka import FrankaObstacleEnv
from afvsgp_gym.envs.scenario import ObstacleSpec
from afvsgp_gym.envs.task_velocity import TaskVelocityLoop, compose_affine
from afvsgp_gym.types import BarrierSet
from afvsgp_gym.validation import check_choice, check_count, check_real

__all__ = ["FrankaObstacleReachEnv"]

#: The obstacle envs' defaults, which the reach task keeps for the plant and the physics.
_FRANKA = FrankaObstacleEnv._DEFAULTS

#: Shoulder (joint 2 axis) position of the Panda base (m), for the reachability check.
_SHOULDER = np.array([0.0, 0.0, 0.333])


@dataclass(frozen=True)
class _Goal:
    """A fixed point as a reference ``(position, velocity, acceleration)`` of time."""

    position: np.ndarray

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        zero = np.zeros(3)
        return self.position, zero, zero


class FrankaObstacleReachEnv(FrankaObstacleEnv):
    r"""Franka Panda moving its end-effector to a goal drawn per reset, past spheres.

    ## Description
    The plant of :class:`~afvsgp_gym.envs.franka.FrankaObstacleEnv` (Panda with hidden
    payload, mass, damping and armature mismatch, whole-arm safety spheres) made into a task
    that an RL agent learns in a few hundred thousand steps: the action is a 3-D end-effector
    velocity command tracked by a kinematic inner loop
    (:class:`~afvsgp_gym.envs.task_velocity.TaskVelocityLoop`), the episode starts at the
    ready pose, and a goal and ``n_obstacles`` static spheres near the straight path to it are
    drawn per reset. The env steps every 4 ms like the other Franka envs, so a
    :class:`~afvsgp_gym.wrappers.SafetyFilter` around it acts at 250 Hz; agents act at a
    lower rate through :class:`~afvsgp_gym.wrappers.ActionRepeat` outside the filter
    (``action_repeat`` = 10 steps suggested, 25 Hz).

    ## Action Space
    ``Box(-1, 1, (3,), float32)``: commanded end-effector velocity ``v_d = max_speed * u``
    (world frame, m/s). Torques ``tau = A(q, q') u + c(q, q')`` are computed at the start of
    each 4 ms period and held, so ``h'' = lf + lg u`` is exact in ``u``:
    ``lg = n' J_s M^-1 A``, ``lf`` includes ``n' J_s M^-1 c`` (``barrier_terms``; see
    :mod:`afvsgp_gym.envs.task_velocity`). A torque above a joint's limit is clipped
    (``info["torque_saturated"]``; the affine form then holds only approximately).

    ## Observation Space
    ``Box(float32)`` of size ``26 + 4 n_obstacles`` (values clipped to the bounds):

    | Slice | Observation | Min | Max | Unit |
    |---|---|---|---|---|
    | 0:7 | joint angles q | -2 pi | 2 pi | rad |
    | 7:14 | joint velocities q' | -20 | 20 | rad/s |
    | 14:17 | end-effector position p | -3 | 3 | m |
    | 17:20 | end-effector velocity | -10 | 10 | m/s |
    | 20:23 | goal g | -3 | 3 | m |
    | 23:26 | g - p | -3 | 3 | m |
    | next 4 per obstacle | centre - p (3), radius (1) | -3 | 3 | m |

    ## Rewards
    Per 4 ms step, as Safety-Gymnasium's goal tasks: ``reward_progress = progress_weight
    (d_prev - d)`` with ``d = |p - g|`` (m), ``reward_time = -time_penalty``, ``reward_ctrl =
    -control_weight |u|^2``, ``reward_cost = -cost_weight * cost`` (contact, self-contact or h < 0),
    ``reward_success = success_bonus`` on the step that reaches the goal; ``reward`` is their
    sum (terms in ``info``). Cost stays a separate signal too (``info["cost"]``), and the
    penalty makes an unfiltered agent learn to avoid the obstacles, a fair baseline.

    ## Starting State and Task
    The ready pose plus uniform joint noise of +-``reset_noise`` rad, at rest. The goal is
    drawn in x in [0.25, 0.65], y in [-0.65, 0.65], z in [0.15, 0.6] m at 0.5-0.75 m from the
    start end-effector and within 0.72 m of the shoulder, with an inverse-kinematics solution
    of the inner loop's arm (joints 1-4, wrist at the ready pose). Each obstacle (radius in
    [0.04, 0.07] m) lies on the start-goal segment with a lateral offset of at most its
    radius + 0.03 m, so the hand's spheres would hit it on the straight path (further
    obstacles: 0.03-0.2 m beyond their radius, beside the path, in the way of a detour); it keeps
    ``start_clearance`` from every safety sphere at the start (see Warm-up), 0.15 m from the
    goal, 0.1 m from every safety sphere in the goal configuration (a learned filter keeps
    a standoff of several centimetres where its model is uncertain), and 0.1 m from the other
    obstacles.

    ## Warm-up (nominal model "zero")
    A learned filter certifies nothing during its warm-up: ``SafetyFilter`` takes
    ``warmup_steps - 1`` = 75 samples (0.3 s) here. Every obstacle starts
    ``start_clearance`` = 0.22 m (surface to surface) from every safety sphere, more than any
    sphere travels in 0.3 s under any command (0.19 m for a constant diagonal command,
    ``sqrt(3) max_speed`` plus the sinking under residual gravity; tests/envs/test_reach.py
    drives the extreme commands), so no warm-up step can have cost, in the first training
    episode of a filter or in an evaluation episode with a fresh filter.

    ## Episode End
    Terminated on success (``|p - g| < goal_tolerance``, ``info["success"]``) or when the
    simulation goes unstable. Truncation by ``TimeLimit``: 1250 steps (5 s).

    ## Info
    The keys of ``FrankaObstacleEnv`` (``cost``, ``h``, ``h_per_barrier``, ``collision``,
    ``delta_b_true``, ``tracking_error`` = goal distance, ``reference_h`` = goal clearance,
    ``unstable``, ``time``) plus ``success``, ``torque_saturated`` and the reward terms.

    ## Arguments
    | Parameter | Default | Description |
    |---|---|---|
    | n_obstacles | 1 | static spheres near the straight path |
    | nominal_model | "zero" | "zero", "kinematic", "perturbed", "exact" |
    | safety_spheres | "arm" | "arm", "ee" or a list of (body, offset, radius) |
    | self_collision | None | barriers between the arm's own links (None: on with "arm") |
    | max_speed | 0.3 | m/s per unit action |
    | task_damping | 200.0 | N s/m, inner loop ``D`` |
    | goal_tolerance | 0.05 | m (as FetchReach and panda-gym) |
    | start_clearance | 0.22 | m, obstacle surface to every safety sphere at the start |
    | progress_weight | 10.0 | reward per m of approach |
    | time_penalty, control_weight | 4e-4, 1e-4 | reward weights per step |
    | cost_weight, success_bonus | 0.2, 1.0 | reward per cost step, on success |
    | warmup_steps | 76 | steps before an obstacle is reachable (filter warm-up 75) |
    | action_repeat | 10 | suggested policy period in steps (read by agents) |
    | payload_mass, mass_scale, damping, friction, armature, plant_seed | as Franka | plant |
    | physics_dt, frame_skip | 0.002, 2 | MuJoCo step and steps per action (4 ms) |
    | reset_noise | 0.02 | rad |
    | obstacle_noise, obstacle_rate, obstacle_delay | as Franka | the camera |
    | velocity_noise, position_noise, push | as Franka | encoders, pushes |
    | render_mode, width, height | None, 480, 480 | |

    ## Version History
    * v0: initial version.
    """

    #: Obstacle radius range (m) and the goal's workspace box (m).
    RADIUS_RANGE = (0.04, 0.07)
    GOAL_BOX = (np.array([0.25, -0.65, 0.15]), np.array([0.65, 0.65, 0.6]))
    GOAL_DISTANCE = (0.5, 0.75)
    GOAL_CLEARANCE = 0.15
    FINAL_CLEARANCE = 0.1
    OBSTACLE_GAP = 0.1
    MAX_REACH = 0.72
    #: The method's learner settings (the RL results were measured with them; the obstacle
    #: scenarios' whole-arm M = 30, P = 500 are not measured on this task)
    ARM_LEARNER_DEFAULTS: dict[str, dict[str, Any]] = {}

    @named_arguments
    def __init__(
        self,
        *,
        n_obstacles: int = 1,
        nominal_model: str = "zero",
        safety_spheres: str | Sequence = "arm",
        self_collision: bool | None = None,
        max_speed: float = 0.3,
        task_damping: float = 200.0,
        goal_tolerance: float = 0.05,
        start_clearance: float = 0.22,
        progress_weight: float = 10.0,
        time_penalty: float = 4e-4,
        control_weight: float = 1e-4,
        cost_weight: float = 0.2,
        success_bonus: float = 1.0,
        warmup_steps: int = 76,
        action_repeat: int = 10,
        reset_noise: float = 0.02,
        # the plant, the physics and rendering as every Franka env
        payload_mass: float = _FRANKA["payload_mass"],
        mass_scale: float | tuple[float, float] = _FRANKA["mass_scale"],
        damping: float = _FRANKA["damping"],
        friction: float = _FRANKA["friction"],
        armature: float = _FRANKA["armature"],
        plant_seed: int = _FRANKA["plant_seed"],
        physics_dt: float = _FRANKA["physics_dt"],
        frame_skip: int = _FRANKA["frame_skip"],
        obstacle_noise: float = _FRANKA["obstacle_noise"],
        obstacle_rate: float | None = _FRANKA["obstacle_rate"],
        obstacle_delay: float = _FRANKA["obstacle_delay"],
        velocity_noise: float = _FRANKA["velocity_noise"],
        position_noise: float = _FRANKA["position_noise"],
        push: dict | None = _FRANKA["push"],
        render_mode: str | None = _FRANKA["render_mode"],
        width: int = _FRANKA["width"],
        height: int = _FRANKA["height"],
    ) -> None:
        n_obs = check_count(n_obstacles, "n_obstacles")
        check_choice("nominal_model", nominal_model, NOMINAL_MODELS)
        self.loop = TaskVelocityLoop(
            max_speed=check_real(max_speed, "max_speed", low=0.0, low_open=True),
            damping=check_real(task_damping, "task_damping", low=0.0, low_open=True),
        )
        self.goal_tolerance = check_real(goal_tolerance, "goal_tolerance", low=0.0,
                                         low_open=True)
        self.start_clearance = check_real(start_clearance, "start_clearance", low=0.0)
        self.progress_weight = check_real(progress_weight, "progress_weight", low=0.0)
        self.time_penalty = check_real(time_penalty, "time_penalty", low=0.0)
        self.cost_weight = check_real(cost_weight, "cost_weight", low=0.0)
        self.success_bonus = check_real(success_bonus, "success_bonus")
        self.action_repeat = check_count(action_repeat, "action_repeat")
        check_real(control_weight, "control_weight", low=0.0)
        r_max = self.RADIUS_RANGE[1]
        parked = [{"position": [2.0 + i, 2.0, 0.0], "radius": r_max} for i in range(n_obs)]
        self._task_ready = False
        super().__init__(
            "static", nominal_model=nominal_model, safety_spheres=safety_spheres,
            self_collision=self_collision,
            payload_mass=payload_mass, mass_scale=mass_scale, damping=damping,
            friction=friction, armature=armature, plant_seed=plant_seed, physics_dt=physics_dt,
            frame_skip=frame_skip, obstacles=parked, warmup_steps=warmup_steps,
            control_weight=control_weight, reset_noise=reset_noise, normalize_action=True,
            obstacle_noise=obstacle_noise, obstacle_rate=obstacle_rate,
            obstacle_delay=obstacle_delay, velocity_noise=velocity_noise,
            position_noise=position_noise, push=push,
            render_mode=render_mode, width=width, height=height)
        # the parent's barrier terms are computed per Nm of joint torque and composed here
        self.action_scale = np.ones(7)
        self._ctrl_per_action = 1.0 / self._gear
        self.action_space = spaces.Box(-1.0, 1.0, (3,), dtype=np.float32)
        lim = np.concatenate(
            [np.full(7, 2 * np.pi), np.full(7, 20.0), np.full(3, 3.0), np.full(3, 10.0),
             np.full(6, 3.0), np.full(4 * n_obs, 3.0)]
        )
        self._obs_high = lim
        self.observation_space = spaces.Box(
            -lim.astype(np.float32), lim.astype(np.float32), dtype=np.float32
        )
        self._saturated = False
        self._ik_data = mujoco.MjData(self.model)
        self._task_ready = True
        self._after_state_change()

    #: The keyword arguments and their defaults (from the signature).
    _DEFAULTS: dict[str, Any] = keyword_defaults(__init__)

    # ------------------------------------------------------------------ task
    @property
    def goal(self) -> np.ndarray:
        """Goal position (m), drawn per reset."""
        return self.reference.position

    def _build_scenario(self, rng: np.random.Generator | None) -> None:
        """The default task (before any reset): a goal 0.55 m to the left of the ready
        end-effector and the obstacles parked far away; :meth:`reset_model` draws tasks."""
        self.reference = _Goal(self.reference_center + np.array([0.0, 0.55, -0.1]))
        self.obstacles = tuple(self._user_obstacles)
        self._obstacle_radii = np.array([ob.radius for ob in self.obstacles])

    def _set_task(self, goal: np.ndarray, obstacles: Sequence[ObstacleSpec]) -> None:
        self.reference = _Goal(np.asarray(goal, dtype=np.float64))
        self.obstacles = tuple(obstacles)  # a fresh tuple: the obstacle constants follow it
        self._obstacle_radii = np.array([ob.radius for ob in obstacles])
        for g, ob in zip(self._obstacle_geoms, obstacles, strict=True):
            self.model.geom_size[g, 0] = ob.radius
            self.model.geom_rbound[g] = ob.radius

    def _goal_configuration(self, q0: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """Sphere centres where the inner loop's arm (joints 1-4, wrist held) puts the
        end-effector at ``goal`` (damped least squares with the loop's posture in the null
        space); None when it does not get within 5 mm."""
        m, d = self.model, self._ik_data
        d.qpos[:] = q0
        jac = np.zeros((3, m.nv))
        n = TaskVelocityLoop.N_ARM
        for _ in range(60):
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            err = goal - d.site_xpos[self._site]
            if err @ err < 2.5e-5:
                return self._sphere_centres(d)
            mujoco.mj_jacSite(m, d, jac, None, self._site)
            ja = jac[:, :n]
            pinv = np.linalg.solve(ja @ ja.T + 1e-3 * np.eye(3), ja).T
            null = np.eye(n) - pinv @ ja
            step = pinv @ np.clip(err, -0.1, 0.1) + 0.1 * null @ (self.q_home - d.qpos)[:n]
            d.qpos[:n] += step
        return None

    def _draw_task(self, rng: np.random.Generator) -> tuple[np.ndarray, list[ObstacleSpec]]:
        """Goal and obstacles for the current start state (rejection sampling, see the class
        docstring)."""
        p0 = self._ee[0]
        start_spheres = self._spheres[0]
        radii = self._sphere_radii
        lo, hi = self.GOAL_BOX
        for _ in range(10_000):
            goal = rng.uniform(lo, hi)
            dist = float(np.linalg.norm(goal - p0))
            if not (self.GOAL_DISTANCE[0] <= dist <= self.GOAL_DISTANCE[1]):
                continue
            if np.linalg.norm(goal - _SHOULDER) > self.MAX_REACH:
                continue
            final = self._goal_configuration(self.data.qpos, goal)
            if final is None:
                continue
            axis = (goal - p0) / dist
            obstacles: list[ObstacleSpec] = []
            for _ in range(200):
                r = float(rng.uniform(*self.RADIUS_RANGE))
                s = float(rng.uniform(0.0, dist))
                side = rng.standard_normal(3)
                side -= (side @ axis) * axis
                side /= max(np.linalg.norm(side), 1e-9)
                lateral = (0.0, r + 0.03) if not obstacles else (r + 0.03, r + 0.2)
                centre = p0 + s * axis + float(rng.uniform(*lateral)) * side
                if np.min(np.linalg.norm(start_spheres - centre, axis=1) - radii) - r < (
                    self.start_clearance
                ):
                    continue
                if np.linalg.norm(goal - centre) - r < self.GOAL_CLEARANCE:
                    continue
                if np.min(np.linalg.norm(final - centre, axis=1) - radii) - r < (
                    self.FINAL_CLEARANCE
                ):
                    continue
                if any(
                    np.linalg.norm(ob.position - centre) - ob.radius - r < self.OBSTACLE_GAP
                    for ob in obstacles
                ):
                    continue
                obstacles.append(ObstacleSpec(centre, r))
                if len(obstacles) == self.n_obstacles:
                    return goal, obstacles
        raise RuntimeError("no feasible reach task found; check the task parameters")

    def reset_model(self) -> np.ndarray:
        self._steps = 0
        noise = self.np_random.uniform(-self.reset_noise, self.reset_noise, 7)
        self.data.qpos[:] = self.q_home + noise
        self.data.qvel[:] = 0.0
        self.data.warning.number[:] = 0
        self._set_task(self.goal, self._user_obstacles)  # parked while drawing
        self._after_state_change()
        goal, obstacles = self._draw_task(self.np_random)
        if not self.perception.exact:  # after the task's draws: the same task either way
            self._reseed_sensing()
        self._set_task(goal, obstacles)
        self._after_state_change()
        self._prev_distance = self._goal_distance()
        return self._get_obs()

    # ------------------------------------------------------------------ dynamics
    def _after_state_change(self) -> None:
        super()._after_state_change()
        if getattr(self, "_task_ready", False):
            d = self._sensed_view.data  # the inner loop reads the encoders (its Jacobian too)
            self._A, self._c = self.loop.affine_torque(
                self._ee_jac, d.qpos, d.qvel, self.q_home
            )

    def _advance(self, u: np.ndarray) -> bool:
        tau = self._A @ u + self._c
        limit = self._gear
        self._saturated = bool(np.any(np.abs(tau) > limit))
        return super()._advance(np.clip(tau, -limit, limit))

    def _compute_barriers(self, kind: str, truth: bool = False) -> BarrierSet:
        torque = self._torque_terms(kind, truth)
        lf, lg = compose_affine(torque.lf, torque.lg, self._A, self._c)
        terms = BarrierSet(torque.derivatives, lf, lg, torque.xi, torque.covariance)
        for arr in (lf, lg):
            arr.flags.writeable = False
        return terms

    def backup_action(self) -> np.ndarray:
        """Zero velocity command: the inner loop damps the end-effector velocity (a
        model-free brake; the arm still sinks slowly under its uncompensated weight)."""
        return np.zeros(3)

    # ------------------------------------------------------------------ gym API
    def _get_obs(self) -> np.ndarray:
        view = self._sensed_view  # what the sensors give
        p, v = view.ee
        g = self.goal
        parts = [view.data.qpos, view.data.qvel, p, v, g, g - p]
        for ob, (po, _, _) in zip(self.obstacles, view.obstacle_states, strict=True):
            parts += [po - p, [ob.radius]]
        obs = np.concatenate(parts)
        np.clip(obs, -self._obs_high, self._obs_high, out=obs)
        return obs.astype(np.float32)

    def _goal_distance(self) -> float:
        err = self._ee[0] - self.goal
        return math.sqrt(float(err @ err))

    def _get_rew(self, u: np.ndarray) -> tuple[float, dict[str, float]]:
        d = self._goal_distance()
        progress = self.progress_weight * (self._prev_distance - d)
        self._prev_distance = d
        ctrl = -self.control_weight * float(u @ u)
        terms = {"reward_progress": progress, "reward_time": -self.time_penalty,
                 "reward_ctrl": ctrl}
        return progress - self.time_penalty + ctrl, terms

    def step(self, action):
        """One 4 ms step (see the class docstring); terminated on success."""
        obs, _, terminated, truncated, info = super().step(action)
        success = info["tracking_error"] < self.goal_tolerance
        r_cost = -self.cost_weight * info["cost"]
        r_success = self.success_bonus if success else 0.0
        reward = (info["reward_progress"] + info["reward_time"] + info["reward_ctrl"] + r_cost
                  + r_success)
        info.update(reward_cost=r_cost, reward_success=r_success, success=bool(success),
                    torque_saturated=self._saturated)
        return obs, reward, terminated or success, truncated, info

    def _reset_info(self) -> dict[str, Any]:
        info = super()._reset_info()
        info.update(success=False, torque_saturated=False)
        return info
