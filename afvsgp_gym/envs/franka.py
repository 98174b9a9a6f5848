"""Franka Panda end-effector tracking past spherical obstacles with a hidden model mismatch."""

from __future__ import annotations

import math
import os
from typing import Any

import mujoco
import numpy as np
from gymnasium import spaces
from gymnasium.envs.mujoco import MujocoEnv

from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs.point_mass import (
    BARRIER_MODELS,
    NOMINAL_MODELS,
    SCENARIOS,
    UnknownArgumentError,
)
from afvsgp_gym.envs.scenario import (
    CyclicReference,
    ObstacleSpec,
    check_action,
    check_choice,
    check_number,
    make_terms,
    parse_obstacles,
    sphere_barrier,
)
from afvsgp_gym.types import BarrierTerms

_BAD_WARNINGS = np.array(
    [
        int(mujoco.mjtWarning.mjWARN_BADQACC),
        int(mujoco.mjtWarning.mjWARN_BADQPOS),
        int(mujoco.mjtWarning.mjWARN_BADQVEL),
    ]
)


class FrankaObstacleEnv(MujocoEnv):
    r"""Franka Panda (torque control) tracking a cyclic end-effector reference past spheres.

    ## Description
    The 7-DoF Panda of ``gymnasium_robotics`` (see :mod:`afvsgp_gym.envs.franka_model`) with
    motor actuators, a fixed gripper and the robot's own gravity compensation of its
    *catalogue* model. The true plant differs from the catalogue: a ``payload_mass`` at the
    flange (not compensated), link masses and inertias scaled by per-link factors drawn from
    ``mass_scale`` with ``plant_seed``, joint ``damping``, ``friction`` (frictionloss) and
    rotor ``armature``. The end-effector (site ``end_effector`` on the gripper axis between
    the finger pads, 4-5 cm above the fingertips, which the 5 cm ``ee_radius`` sphere just
    covers) tracks the reference of paper Fig. 3; the safety filter keeps it out of the
    obstacles.

    Gravity compensation, as with the real robot's torque interface: commanded torques act on
    top of the robot's compensation of its catalogue model. Each link of the true plant gets
    MuJoCo ``gravcomp = m_catalogue / m_true`` (set in the MjSpec before compiling), the
    payload gravcomp 0, so ``(m_true - m_catalogue) g`` per link and the full payload weight
    remain as unknown residual gravity.

    Physics: MuJoCo step ``physics_dt`` = 2 ms (Euler, implicit joint damping), ``frame_skip``
    = 2, so the control period ``dt`` = 4 ms (250 Hz); ``render_fps`` = 250.

    ## Barrier (paper eqs. 44-46)
    Per obstacle ``h = |p_ee - p_obs| - (r_obs + ee_radius)``, relative degree 2:
    ``h'' = n.(J q'' + J' q' - a_obs) + (|v_rel|^2 - (n.v_rel)^2)/|d|``, ``n = d/|d|``.
    With ``q'' = q''_0 + M^-1 diag(action_scale) u`` (``q''_0``: acceleration at u = 0 from passive,
    bias, residual gravity and joint-limit forces), ``barrier_terms(model)`` gives
    ``lf = n.(J q''_0 + J' q' - a_obs) + curvature`` and ``lg = n' J M^-1 diag(action_scale)``:

    - ``"true"``: the true plant (for evaluation / oracle only).
    - ``"nominal"`` by ``nominal_model``: ``"zero"`` lf = lg = 0 (paper section VI; the
      derivatives [h, h'] are still measured); ``"kinematic"`` kinematics and obstacle motion
      known: lf = n.(J' q' - a_obs) + curvature, lg = 0; ``"perturbed"`` a second model with
      the catalogue parameters (no payload, scale 1, no damping/friction/armature, full
      gravity compensation); ``"exact"`` the true plant (delta_b_true = 0).
    - features ``xi = [q (7), q' (7), p_ee - p_obs (3), v_ee - v_obs (3)]``, feature_dim 20
      (the paper's b = 20).

    Friction (frictionloss) and joint-limit forces come from MuJoCo's constraint solver and are
    evaluated at u = 0, so with ``friction > 0`` the split into lf and lg is exact only while
    the joints slide (static friction couples them); ``friction=0`` makes it exact.

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
    | next 3n | obstacle centres | -5 | 5 | body obstacle<i> | m |
    | next 3n | obstacle velocities | -5 | 5 | | m/s |
    | next 3 | reference position | -3 | 3 | body reference | m |
    | next 3 | reference velocity | -10 | 10 | | m/s |
    | next 3 | reference acceleration | -50 | 50 | | m/s^2 |

    ## Rewards
    ``reward = reward_tracking + reward_ctrl``, ``reward_tracking = -tracking_weight
    |p_ee - r|`` (m), ``reward_ctrl = -control_weight |u|^2``; terms in ``info``.
    ``info["cost"] = 1.0`` if any h < 0 (Safety-Gymnasium convention).

    ## Starting State
    The ready pose ``q = (0, -0.785, 0, -2.356, 0, 0, 0.785)`` (end-effector at the reference
    centre, about (0.307, 0, 0.487) m, hand down) plus uniform noise of +-``reset_noise`` rad,
    at rest.

    ## Episode End
    Terminated when the simulation goes unstable (non-finite state or a MuJoCo bad-state
    warning; ``info["unstable"] = True``). Truncation by ``TimeLimit``: 4000 steps (16 s).

    ## Info
    ``cost``, ``h`` (min over obstacles), ``h_per_obstacle``, ``collision`` (an arm collision
    geom overlaps an obstacle, ``mj_geomDistance`` < 0), ``delta_b_true`` (true minus nominal
    h'' for the applied action at the pre-step state), ``unstable``, ``time``,
    ``reward_tracking``, ``reward_ctrl``.

    ## Scenarios (c = reference centre, y = axis of the cyclic motion)
    Reference: ``c + a(t) sin(2 pi t / 4 s)`` along y, amplitude 0.04 m during the
    ``warmup_steps`` (500 = 2 s), ramped to 0.28 m over 1 s; static scenario: turns to z at
    ``switch_time`` (10 s). Peak reference speed 0.44 m/s, acceleration 0.7 m/s^2.

    - ``"static"``: sphere r = 0.05 m at c + (0, 0.20, -0.07): the full y motion passes 7 cm
      above its centre, 3 cm inside the safe-set boundary (R = r + ee_radius = 0.1 m; the
      zero-model tracker, sagging under the residual gravity, goes about 6 cm in), so the
      filter must act; the warm-up motion stays >= 6 cm outside the boundary.
    - ``"dynamic"``: sphere r = 0.05 m rests at c + (0.5, 0.15, -0.07) during warm-up, then
      moves in -x onto the path, c + (0, 0.15, -0.07), with peak speed ``obstacle_speed``
      (0.15 m/s; the arm retreats at > 0.5 m/s) and stays there. No switch unless set.
    - ``"random"``: static or dynamic with radius in [0.04, 0.07] m, position along y in
      [R + 0.10, 0.24] m on either side (warm-up clearance >= 6 cm), offset in z in
      [-0.09, -0.06] m and x in +-0.02 m, approach from +x or from outside along y at
      0.3-0.5 m, peak speed in [0.05, 0.2] m/s and an optional switch, drawn per reset.

    The obstacles sit 6-9 cm below the path, so the end-effector passes over them and the
    hand (about 17 cm wide, 4-13 cm above the end-effector site) clears them whenever h >= 0:
    the barrier protects the end-effector sphere only (as in the paper), and ``collision``
    reports any arm geometry. With the exact model a CBF-filtered run keeps h >= 0 with no arm
    collision in every scenario and seed tested (tests/envs/test_franka.py); a filter that
    routes the end-effector under or beside an obstacle can keep h >= 0 and still touch it
    with the hand (raise ``ee_radius`` for a more conservative envelope).

    ## Arguments
    | Parameter | Default | Description |
    |---|---|---|
    | scenario | "static" | "static", "dynamic", "random" |
    | nominal_model | "zero" | "zero", "kinematic", "perturbed", "exact" |
    | payload_mass | 1.0 | kg at the flange, not gravity compensated |
    | mass_scale | (0.9, 1.3) | per-link mass/inertia factor range (or one float) |
    | damping | 1.0 | joint damping, Nm s/rad (true plant) |
    | friction | 0.0 | joint frictionloss, Nm (true plant) |
    | armature | 0.1 | rotor inertia, kg m^2 (true plant) |
    | plant_seed | 0 | seed of the per-link mass factors |
    | physics_dt, frame_skip | 0.002, 2 | MuJoCo step (s) and steps per action |
    | ee_radius | 0.05 | m, sphere around the end-effector site |
    | obstacles | None | list of dicts (position, radius[, start, start_time, speed]) |
    | obstacle_speed | 0.15 | m/s, dynamic scenario |
    | switch_time | None | s; None = 10 s static, none otherwise |
    | warmup_steps | 500 | steps with obstacles far away (>= 250) |
    | tracking_weight, control_weight | 1.0, 0.01 | reward weights |
    | reset_noise | 0.01 | rad |
    | normalize_action | True | action in [-1, 1] (tau = u tau_max); False: action = tau in Nm |
    | brake_gain | 1.0 | ``backup_action``: tau = -brake_gain tau_max q' (per rad/s), saturated |
    | render_mode, width, height | None, 480, 480 | "rgb_array", "depth_array", "human" (display) |

    Custom ``obstacles`` replace the scenario's (the reference stays): each dict gives the
    final ``position`` and ``radius``; with ``start`` the sphere rests there and moves to
    ``position`` from ``start_time`` (default: the end of the warm-up) at peak ``speed``
    (m/s, default 0.2). Keeping them clear of the warm-up motion is then up to the caller.

    ## Version History
    - v0: initial version.
    """

    # "human" needs a display (GLFW window); headless machines render offscreen (MUJOCO_GL=egl)
    metadata = {
        "render_modes": ["rgb_array", "depth_array"]
        + (["human"] if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") else []),
        "render_fps": 250,
    }

    _DEFAULTS: dict[str, Any] = dict(
        nominal_model="zero",
        payload_mass=1.0,
        mass_scale=(0.9, 1.3),
        damping=1.0,
        friction=0.0,
        armature=0.1,
        plant_seed=0,
        physics_dt=0.002,
        frame_skip=2,
        ee_radius=0.05,
        obstacles=None,
        obstacle_speed=0.15,
        switch_time=None,
        warmup_steps=500,
        tracking_weight=1.0,
        control_weight=0.01,
        reset_noise=0.01,
        normalize_action=True,
        brake_gain=1.0,
        render_mode=None,
        width=480,
        height=480,
    )
    relative_degree = 2
    AMPLITUDE, WARMUP_AMPLITUDE, PERIOD = 0.28, 0.04, 4.0

    def __init__(self, scenario: str = "static", **kwargs: Any) -> None:
        unknown = sorted(set(kwargs) - set(self._DEFAULTS))
        if unknown:
            raise UnknownArgumentError(
                f"unknown argument(s) {unknown}; valid: {['scenario', *self._DEFAULTS]}"
            )
        cfg = {**self._DEFAULTS, **kwargs}
        self.scenario = check_choice("scenario", scenario, SCENARIOS)
        self.nominal_model = check_choice("nominal_model", cfg["nominal_model"], NOMINAL_MODELS)
        for name in ("payload_mass", "damping", "friction", "armature", "reset_noise"):
            cfg[name] = check_number(name, cfg[name], strictly_positive=False)
        for name in ("physics_dt", "ee_radius", "obstacle_speed"):
            cfg[name] = check_number(name, cfg[name], strictly_positive=True)
        frame_skip = int(cfg["frame_skip"])
        if frame_skip < 1:
            raise ValueError(f"frame_skip must be >= 1, got {cfg['frame_skip']}")
        self.warmup_steps = int(cfg["warmup_steps"])
        if self.warmup_steps < 0:
            raise ValueError(f"warmup_steps must be >= 0, got {cfg['warmup_steps']}")
        st = cfg["switch_time"]
        if st is not None and not (float(st) > 0):
            raise ValueError(f"switch_time must be > 0 or None, got {st}")
        self._switch_time_arg = None if st is None else float(st)
        self.ee_radius = float(cfg["ee_radius"])
        self.obstacle_speed = float(cfg["obstacle_speed"])
        self.tracking_weight = float(cfg["tracking_weight"])
        self.control_weight = float(cfg["control_weight"])
        self.reset_noise = float(cfg["reset_noise"])
        self.normalize_action = bool(cfg["normalize_action"])
        self.brake_gain = check_number("brake_gain", cfg["brake_gain"], strictly_positive=False)
        physics_dt = float(cfg["physics_dt"])
        self._control_dt = physics_dt * frame_skip
        self._user_obstacles = (
            None
            if cfg["obstacles"] is None
            else parse_obstacles(cfg["obstacles"], 3, self.warmup_steps * self._control_dt)
        )
        self.plant = self._plant_parameters(cfg)
        n_obs = 1 if self._user_obstacles is None else len(self._user_obstacles)
        radii = (
            (0.05,) * n_obs
            if self._user_obstacles is None
            else tuple(o.radius for o in self._user_obstacles)
        )
        if self.scenario == "random" and self._user_obstacles is None:
            radii = (0.07,)  # drawn radii <= 0.07: the visual sphere is rescaled per reset
        self._scene = fm.SceneOptions(radii, self.ee_radius, physics_dt)
        render_mode = cfg["render_mode"]
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
        self._obs_high = lim
        obs_space = spaces.Box(-lim.astype(np.float32), lim.astype(np.float32), dtype=np.float32)
        super().__init__(
            fm.asset_dir(),  # the model is assembled in _initialize_simulation
            frame_skip,
            obs_space,
            render_mode=render_mode,
            width=int(cfg["width"]),
            height=int(cfg["height"]),
            default_camera_config={
                "distance": 1.5,
                "azimuth": 200.0,
                "elevation": -20.0,
                "lookat": np.array([0.3, 0.0, 0.45]),
            },
        )
        m = self.model
        self._site = m.site(fm.EE_SITE).id
        self._ee_body = m.body(fm.EE_BODY).id
        self._gear = m.actuator_gear[:, 0].copy()
        if self.normalize_action:
            self.action_scale = self._gear.copy()  # Nm per action unit
        else:
            self.action_scale = np.ones(7)
            self.action_space = spaces.Box(
                -self._gear.astype(np.float32), self._gear.astype(np.float32), dtype=np.float32
            )
        self._ctrl_per_action = self.action_scale / self._gear
        self._arm_geoms = fm.arm_collision_geoms(m)
        self._arm_rbound = m.geom_rbound[self._arm_geoms].copy()
        self._obstacle_geoms = np.array([m.geom(f"obstacle{i}").id for i in range(n_obs)])
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
            self.nominal_mj_model = fm.build_model(fm.PlantParameters(), self._scene)
            self.nominal_mj_data = mujoco.MjData(self.nominal_mj_model)
        else:
            self.nominal_mj_model = self.model if self.nominal_model == "exact" else None
            self.nominal_mj_data = None
        self._build_scenario(None)
        self._steps = 0
        self._terms_cache: dict[str, list[BarrierTerms]] = {}
        self._jac = np.zeros((3, m.nv))
        self._jacdot = np.zeros((3, m.nv))
        self._jminv = np.zeros((3, m.nv))

    # ------------------------------------------------------------------ construction
    def _plant_parameters(self, cfg: dict[str, Any]) -> fm.PlantParameters:
        scale = cfg["mass_scale"]
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
            factors = np.random.default_rng(int(cfg["plant_seed"])).uniform(lo, hi, 9)
            factors[8] = factors[7]  # the two fingers alike
        if not np.all(factors > 0):
            raise ValueError(f"mass_scale must be > 0, got {scale}")
        return fm.PlantParameters(
            mass_scale=factors,
            payload_mass=float(cfg["payload_mass"]),
            damping=np.full(7, float(cfg["damping"])),
            frictionloss=np.full(7, float(cfg["friction"])),
            armature=np.full(7, float(cfg["armature"])),
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
            big_r = radius + self.ee_radius
            along = float(rng.uniform(big_r + 0.10, max(big_r + 0.10, 0.24)))
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
        if kind == "static":
            obstacles = [ObstacleSpec(centre, radius)]
        else:
            obstacles = [ObstacleSpec(centre, radius, centre + start_off, t_w, speed)]
        self.obstacles = obstacles if self._user_obstacles is None else self._user_obstacles
        if self._user_obstacles is None and self.scenario == "random":
            # visual sphere follows the drawn radius
            self.model.geom_size[self._obstacle_geoms[0], 0] = radius
        self.reference = CyclicReference(
            center=c.copy(),
            axis1=ey,
            axis2=ez,
            amplitude=self.AMPLITUDE,
            warmup_amplitude=self.WARMUP_AMPLITUDE,
            period=self.PERIOD,
            ramp_start=t_w,
            ramp_duration=1.0,
            switch_time=switch,
        )

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
        self._kin = self._kinematics(self.model, d)
        # per obstacle: (h, h', n, curvature, xi), shared by every model's terms and the info
        p, v = self._kin[0], self._kin[1]
        qq = np.concatenate([d.qpos, d.qvel])
        self._geo = []
        for ob, (po, vo, _) in zip(self.obstacles, self._obs_states, strict=True):
            h, hd, n, curv = sphere_barrier(p, v, po, vo, ob.radius + self.ee_radius)
            xi = np.concatenate([qq, p - po, v - vo])
            xi.flags.writeable = False
            self._geo.append((h, hd, n, curv, xi))
        self._terms_cache = {}

    def _place_markers(self) -> None:
        t = self.time
        self._obs_states = [ob.state(t) for ob in self.obstacles]
        for k, (p, _, _) in zip(self._obstacle_mocap, self._obs_states, strict=True):
            self.data.mocap_pos[k] = p
        self._ref_state = self.reference.state(t)
        self.data.mocap_pos[self._ref_mocap] = self._ref_state[0]

    # ------------------------------------------------------------------ barrier
    def _kinematics(self, model, data):
        """EE position, velocity, J (3, nv) and J' q' for a forwarded (model, data)."""
        jac, jacdot = self._jac, self._jacdot
        mujoco.mj_jacSite(model, data, jac, None, self._site)
        p = data.site_xpos[self._site].copy()
        mujoco.mj_jacDot(model, data, jacdot, None, p, self._ee_body)
        qd = data.qvel
        return p, jac @ qd, jac.copy(), jacdot @ qd

    def _compute_terms(self, kind: str) -> list[BarrierTerms]:
        m, d = self.model, self.data
        jac, jdqd = self._kin[2], self._kin[3]
        if kind == "exact" or (kind == "perturbed" and self.nominal_mj_data is None):
            mujoco.mj_solveM(m, d, self._jminv, jac)
            a_free = jac @ d.qacc + jdqd
            gain = self._jminv * self.action_scale
        elif kind == "perturbed":
            mn, dn = self.nominal_mj_model, self.nominal_mj_data
            dn.qpos[:] = d.qpos
            dn.qvel[:] = d.qvel
            dn.ctrl[:] = 0.0
            mujoco.mj_forward(mn, dn)
            mujoco.mj_solveM(mn, dn, self._jminv, jac)
            a_free = jac @ dn.qacc + jdqd
            gain = self._jminv * self.action_scale
        out = []
        for (h, hd, n, curv, xi), (_, _, ao) in zip(self._geo, self._obs_states, strict=True):
            if kind == "zero":
                lf, lg = 0.0, np.zeros(7)
            elif kind == "kinematic":
                lf, lg = float(n @ (jdqd - ao)) + curv, np.zeros(7)
            else:
                lf, lg = float(n @ (a_free - ao)) + curv, n @ gain
            out.append(make_terms(h, hd, lf, lg, xi))
        return out

    def barrier_terms(self, model: str = "nominal") -> list[BarrierTerms]:
        """One BarrierTerms per obstacle at the current state (see class docstring)."""
        check_choice("model", model, BARRIER_MODELS)
        kind = "exact" if model == "true" else self.nominal_model
        if kind not in self._terms_cache:
            self._terms_cache[kind] = self._compute_terms(kind)
        return self._terms_cache[kind]

    def backup_action(self) -> np.ndarray:
        """Model-free brake for the safety filter's backup: joint damping torque
        ``tau = -brake_gain tau_max q'`` saturated at the torque limits, as an action.

        It opposes every joint velocity, so it removes kinetic energy whatever the plant's
        inertia, payload or friction (no model needed); ``SafetyFilter`` applies it when the
        chance-constrained program is infeasible. It does not hold position: the arm sinks
        under the uncompensated weight at ~0.1 rad/s. Gains above ~1.5 make the base joint
        chatter at the 4 ms control period (discrete-time damping limit).
        """
        u = -self.brake_gain * np.asarray(self.data.qvel[:7], dtype=np.float64)
        np.clip(u, -1.0, 1.0, out=u)
        return u * (1.0 if self.normalize_action else self._gear)

    # ------------------------------------------------------------------ gym API
    def _ee(self) -> tuple[np.ndarray, np.ndarray]:
        return self._kin[0], self._kin[1]

    def _get_obs(self) -> np.ndarray:
        p, v = self._ee()
        r, rd, rdd = self._ref_state
        obs = np.concatenate(
            [self.data.qpos, self.data.qvel, p, v]
            + [s[0] for s in self._obs_states]
            + [s[1] for s in self._obs_states]
            + [r, rd, rdd]
        )
        np.clip(obs, -self._obs_high, self._obs_high, out=obs)
        return obs.astype(np.float32)

    def _h_values(self) -> np.ndarray:
        return np.array([g[0] for g in self._geo])

    def _collision(self) -> bool:
        m, d = self.model, self.data
        for k, g_obs in enumerate(self._obstacle_geoms):
            po = self._obs_states[k][0]
            diff = d.geom_xpos[self._arm_geoms] - po
            reach = self._arm_rbound + self.obstacles[k].radius
            near = np.einsum("ij,ij->i", diff, diff) < reach * reach
            if not near.any():
                continue
            for g in self._arm_geoms[near]:
                if mujoco.mj_geomDistance(m, d, int(g), int(g_obs), 0.01, None) < 0:
                    return True
        return False

    def _safety_info(self) -> dict[str, Any]:
        hs = self._h_values()
        unsafe = bool(np.any(hs < 0))
        return {
            "cost": 1.0 if unsafe else 0.0,
            "h": float(np.min(hs)),
            "h_per_obstacle": hs,
            "collision": self._collision(),
        }

    def _get_rew(self, u: np.ndarray) -> tuple[float, dict[str, float]]:
        p = self.data.site_xpos[self._site]
        track = -self.tracking_weight * float(np.linalg.norm(p - self._ref_state[0]))
        ctrl = -self.control_weight * float(u @ u)
        return track + ctrl, {"reward_tracking": track, "reward_ctrl": ctrl}

    def reset_model(self) -> np.ndarray:
        self._steps = 0
        if self.scenario == "random":
            self._build_scenario(self.np_random)
        noise = self.np_random.uniform(-self.reset_noise, self.reset_noise, 7)
        self.data.qpos[:] = self.q_home + noise
        self.data.qvel[:] = 0.0
        self.data.warning.number[:] = 0
        self._after_state_change()
        return self._get_obs()

    def _get_reset_info(self) -> dict[str, Any]:
        info = self._safety_info()
        info.update(delta_b_true=np.zeros(self.n_obstacles), unstable=False, time=0.0)
        return info

    def step(self, action):
        a = check_action(action, self.action_space.shape)
        u = np.clip(a, self.action_space.low, self.action_space.high)
        true_terms = self.barrier_terms("true")
        nom_terms = self.barrier_terms("nominal")
        delta = np.array(
            [
                (tt.lf + tt.lg @ u) - (tn.lf + tn.lg @ u)
                for tt, tn in zip(true_terms, nom_terms, strict=True)
            ]
        )
        m, d = self.model, self.data
        warn_before = int(d.warning.number[_BAD_WARNINGS].sum())
        d.ctrl[:] = u * self._ctrl_per_action
        mujoco.mj_step(m, d, nstep=self.frame_skip)
        self._steps += 1
        warn_after = int(d.warning.number[_BAD_WARNINGS].sum())
        unstable = warn_after > warn_before or not math.isfinite(float(d.qpos.sum() + d.qvel.sum()))
        if unstable:
            d.qpos[:] = np.nan_to_num(d.qpos)
            d.qvel[:] = 0.0
        self._after_state_change()
        reward, reward_info = self._get_rew(u)
        info = self._safety_info()
        info.update(reward_info)
        info.update(delta_b_true=delta, unstable=unstable, time=self.time)
        if self.render_mode == "human":
            self.render()
        return self._get_obs(), reward, unstable, False, info
