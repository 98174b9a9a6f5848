"""Point mass (double integrator with unknown mass and linear drag) avoiding spheres."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from afvsgp_gym.envs._render2d import Canvas
from afvsgp_gym.envs.base import (
    BARRIER_MODELS,
    NOMINAL_MODELS,
    SCENARIOS,
    ObstacleTask,
    keyword_defaults,
    named_arguments,
)
from afvsgp_gym.envs.scenario import (
    CyclicReference,
    ObstacleSpec,
    parse_obstacles,
    sphere_barriers,
)
from afvsgp_gym.types import BarrierSet
from afvsgp_gym.validation import check_choice, check_real


class PointMassObstacleEnv(ObstacleTask, gym.Env):
    r"""Point mass tracking a cyclic reference past spherical obstacles (analytic, fast).

    ## Description
    A point (radius ``agent_radius``) in 2D or 3D with true dynamics
    ``mass * p'' = max_force * u - drag * p'`` (u in [-1, 1]^dim). The controller's nominal model
    does not know ``mass``/``drag`` (see ``nominal_model``). The reference moves cyclically along
    the x axis ("y" in the paper's Fig. 3) with an amplitude that stays small during the first
    ``warmup_steps`` and then grows so that the path passes through the obstacle; at
    ``switch_time`` the motion turns to the y axis ("z", unseen data). This is the analytic
    twin of the Franka environment: same barrier, same info keys, closed-form ground truth.

    Integration is exact for a zero-order-hold action (matrix exponential of the linear
    drag dynamics), so ``dt`` is both the control period and the integration step.

    ## Barrier (paper eqs. 44-46)
    One barrier per obstacle (``n_barriers = n_obstacles``),
    ``h = |p - p_obs| - (r_obs + agent_radius)``, relative degree 2:
    ``h'' = n.(p'' - a_obs) + (|v_rel|^2 - (n.v_rel)^2)/|d|`` with ``n = d/|d|``,
    ``d = p - p_obs``, ``v_rel = p' - v_obs``. ``barrier_terms(model)`` returns
    ``BarrierTerms(derivatives=[h, h'], lf, lg, xi)``:

    - ``"true"``: ``lf = n.(-drag/mass p' - a_obs) + curvature``, ``lg = n max_force/mass``.
    - ``"nominal"`` by ``nominal_model``: ``"zero"`` lf = 0, lg = 0 (paper section VI);
      ``"kinematic"`` lf = -n.a_obs + curvature, lg = 0; ``"perturbed"`` the true formulas with
      ``nominal_mass``/``nominal_drag``; ``"exact"`` the true formulas.
    - features ``xi = [p, p', p - p_obs, p' - v_obs]`` (``feature_dim = 4 * dim``).

    ## Action Space
    ``Box(-1, 1, (dim,), float32)``: force = ``max_force * u`` (N). Out-of-range actions are
    clipped; NaN/inf or a wrong shape raise ValueError before anything is integrated.

    ## Observation Space
    ``Box(float32)`` of size ``6 dim + 2 dim n_obstacles``:

    | Slice | Observation | Min | Max | Unit |
    |---|---|---|---|---|
    | 0:d | position p | -10 | 10 | m |
    | d:2d | velocity p' | -20 | 20 | m/s |
    | next n d | obstacle centres | -10 | 10 | m |
    | next n d | obstacle velocities | -20 | 20 | m/s |
    | next d | reference position | -10 | 10 | m |
    | next d | reference velocity | -20 | 20 | m/s |
    | next d | reference acceleration | -100 | 100 | m/s^2 |

    Values are clipped to the bounds.

    ## Rewards
    ``reward = reward_tracking + reward_ctrl`` with ``reward_tracking = -tracking_weight |p - r|``
    and ``reward_ctrl = -control_weight |u|^2`` (both in ``info``). Safety is a separate signal:
    ``info["cost"] = 1.0`` if any ``h < 0`` (Safety-Gymnasium convention).

    ## Starting State
    At the reference start (centre) at rest, plus uniform noise of +-``reset_noise`` m.

    ## Episode End
    Terminated if the state is not finite (``info["unstable"] = True``) or the point leaves
    ``|p|_inf <= 5`` m. Truncation by ``TimeLimit`` (1500 steps = 15 s when registered).

    ## Info
    ``cost``, ``h`` (min over barriers), ``h_per_barrier``, ``collision`` (any h < 0),
    ``delta_b_true`` (true minus nominal h'' for the applied action at the pre-step state, per
    barrier), ``tracking_error`` (|p - r|), ``reference_h`` (clearance of an ``agent_radius``
    sphere at the reference point from every obstacle), ``unstable``, ``time``,
    ``reward_tracking``, ``reward_ctrl``.

    ## Scenarios and geometry (defaults, dim = 2; third axis z in 3D)
    - ``"static"``: reference centre 0, amplitude 0.5 m (0.1 m during warm-up), period 3 s,
      amplitude ramp over 1 s after warm-up, switch to the y axis at ``switch_time`` = 9 s.
      Obstacle r = 0.1 m at (0.35, 0.03): the full path runs through it, the warm-up path stays
      >= 0.1 m clear of it.
    - ``"dynamic"``: obstacle r = 0.1 m rests at (0.3, 0.8) during warm-up, then moves to
      (0.3, 0.04), onto the path, with peak speed ``obstacle_speed`` (0.3 m/s, far below what
      the point can reach: max_force/mass = 3.3 m/s^2). No switch unless ``switch_time`` set.
    - ``"random"``: one of the two, with radius in [0.07, 0.11] m, position along the path in
      [r + 0.22, 0.45] m (either side; the warm-up path stays >= 0.07 m clear), offset
      +-0.06 m, speed in [0.15, 0.4] m/s, approach side and distance (0.6-1 m) and an optional
      switch time drawn from ``self.np_random`` at each reset.

    ## Arguments
    | Parameter | Default | Description |
    |---|---|---|
    | scenario | "static" | one of "static", "dynamic", "random" |
    | dim | 2 | 2 or 3 |
    | dt | 0.01 | control period and integration step (s) |
    | mass, drag | 1.5, 0.8 | true plant (kg, N s/m) |
    | nominal_model | "zero" | "zero", "kinematic", "perturbed", "exact" |
    | nominal_mass, nominal_drag | 1.0, 0.0 | parameters of the "perturbed" model |
    | max_force | 5.0 | N per unit action |
    | brake_gain | 2.0 | ``backup_action``: u = -brake_gain p' (per m/s), saturated |
    | agent_radius | 0.05 | m |
    | obstacles | None | list of dicts (position, radius[, start, start_time, speed]) |
    | obstacle_speed | 0.3 | m/s, dynamic scenario |
    | switch_time | None | s; None = scenario default (9 s static, no switch dynamic) |
    | warmup_steps | 300 | steps during which obstacles are far (>= 250) |
    | tracking_weight, control_weight | 1.0, 0.01 | reward weights |
    | reset_noise | 0.01 | m |
    | render_mode | None | "rgb_array" |

    Custom ``obstacles`` replace the scenario's (the reference stays): each dict gives the
    final ``position`` and ``radius``; with ``start`` the sphere rests there and moves to
    ``position`` from ``start_time`` (default: the end of the warm-up) at peak ``speed``
    (m/s, default 0.2). Keeping them clear of the warm-up motion is then up to the caller.

    ## Version History
    - v0: initial version.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 100}

    workspace_limit = 5.0

    @named_arguments
    def __init__(
        self,
        scenario: str = "static",
        *,
        dim: int = 2,
        dt: float = 0.01,
        mass: float = 1.5,
        drag: float = 0.8,
        nominal_model: str = "zero",
        nominal_mass: float = 1.0,
        nominal_drag: float = 0.0,
        max_force: float = 5.0,
        agent_radius: float = 0.05,
        obstacles: Sequence[dict] | None = None,
        obstacle_speed: float = 0.3,
        switch_time: float | None = None,
        warmup_steps: int = 300,
        tracking_weight: float = 1.0,
        control_weight: float = 0.01,
        reset_noise: float = 0.01,
        brake_gain: float = 2.0,
        render_mode: str | None = None,
    ) -> None:
        self.scenario = check_choice("scenario", scenario, SCENARIOS)
        self.nominal_model = check_choice("nominal_model", nominal_model, NOMINAL_MODELS)
        self.dim = int(dim)
        if self.dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim}")
        dt = check_real(dt, "dt", low=0.0, low_open=True)
        mass = check_real(mass, "mass", low=0.0, low_open=True)
        nominal_mass = check_real(nominal_mass, "nominal_mass", low=0.0, low_open=True)
        max_force = check_real(max_force, "max_force", low=0.0, low_open=True)
        agent_radius = check_real(agent_radius, "agent_radius", low=0.0, low_open=True)
        obstacle_speed = check_real(obstacle_speed, "obstacle_speed", low=0.0, low_open=True)
        drag = check_real(drag, "drag", low=0.0)
        nominal_drag = check_real(nominal_drag, "nominal_drag", low=0.0)
        tracking_weight = check_real(tracking_weight, "tracking_weight", low=0.0)
        control_weight = check_real(control_weight, "control_weight", low=0.0)
        reset_noise = check_real(reset_noise, "reset_noise", low=0.0)
        self.dt = float(dt)
        self.mass, self.drag = float(mass), float(drag)
        self.nominal_mass, self.nominal_drag = float(nominal_mass), float(nominal_drag)
        self.max_force = float(max_force)
        self.brake_gain = check_real(brake_gain, "brake_gain", low=0.0)
        self.agent_radius = self.tracking_radius = float(agent_radius)
        self.obstacle_speed = float(obstacle_speed)
        self.warmup_steps = int(warmup_steps)
        if self.warmup_steps < 0:
            raise ValueError(f"warmup_steps must be >= 0, got {warmup_steps}")
        st = switch_time
        if st is not None and not (float(st) > 0):
            raise ValueError(f"switch_time must be > 0 or None, got {st}")
        self._switch_time_arg = None if st is None else float(st)
        self.tracking_weight = float(tracking_weight)
        self.control_weight = float(control_weight)
        self.reset_noise = float(reset_noise)
        self._user_obstacles = (
            None
            if obstacles is None
            else parse_obstacles(obstacles, self.dim, self.warmup_steps * self.dt)
        )
        if render_mode is not None:
            check_choice("render_mode", render_mode, self.metadata["render_modes"])
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.dt))}

        self.axes = np.eye(self.dim)
        self._build_scenario(None)
        self.n_obstacles = self.n_barriers = len(self.obstacles)
        self.barrier_names = tuple(f"agent/obstacle{i}" for i in range(self.n_obstacles))
        self.feature_dim = 4 * self.dim
        d, n = self.dim, self.n_obstacles
        lim = np.concatenate(
            [np.full(d, 10.0), np.full(d, 20.0), np.full(n * d, 10.0), np.full(n * d, 20.0)]
            + [np.full(d, 10.0), np.full(d, 20.0), np.full(d, 100.0)]
        )
        self._obs_high = lim
        self.observation_space = spaces.Box(-lim.astype(np.float32), lim.astype(np.float32))
        self.action_space = spaces.Box(-1.0, 1.0, (d,), dtype=np.float32)
        self._p = np.zeros(d)
        self._v = np.zeros(d)
        self._steps = 0
        self._after_state_change()

    #: The keyword arguments and their defaults (from the signature; the ``## Arguments``
    #: table is tested against them).
    _DEFAULTS: dict[str, Any] = keyword_defaults(__init__)

    # ------------------------------------------------------------------ scenario
    def _build_scenario(self, rng: np.random.Generator | None) -> None:
        e1, e2 = self.axes[0], self.axes[1]
        off = self.axes[2] if self.dim == 3 else e2
        t_w = self.warmup_steps * self.dt
        kind, switch = self.scenario, self._switch_time_arg
        along, offset, radius, speed, side, far = 0.35, 0.03, 0.1, self.obstacle_speed, 1.0, 0.8
        if kind == "random" and rng is not None:
            kind = "static" if rng.random() < 0.5 else "dynamic"
            # warm-up path |x| <= 0.1 stays >= 0.07 m clear: along >= 0.1 + R + 0.07
            radius = float(rng.uniform(0.07, 0.11))
            along = float(rng.uniform(radius + 0.22, 0.45)) * (1.0 if rng.random() < 0.5 else -1.0)
            offset = float(rng.uniform(-0.06, 0.06))
            speed = float(rng.uniform(0.15, 0.4))
            side = 1.0 if rng.random() < 0.5 else -1.0
            far = float(rng.uniform(0.6, 1.0))
            if switch is None and rng.random() < 0.5:
                switch = float(rng.uniform(t_w + 4.0, t_w + 8.0))
        elif kind == "random":
            kind = "static"
        if switch is None:
            switch = 9.0 if kind == "static" and self.scenario == "static" else np.inf
        if kind == "static":
            obstacles = [ObstacleSpec(along * e1 + offset * off, radius)]
        else:
            along = 0.3 if self.scenario == "dynamic" else along
            offset = 0.04 if self.scenario == "dynamic" else offset
            end = along * e1 + offset * off
            start = along * e1 + side * far * off
            obstacles = [ObstacleSpec(end, radius, start, t_w, speed)]
        if self._user_obstacles is not None:
            obstacles = self._user_obstacles
        self.obstacles = tuple(obstacles)
        self.reference = CyclicReference(
            center=np.zeros(self.dim),
            axis1=e1,
            axis2=e2,
            amplitude=0.5,
            warmup_amplitude=0.1,
            period=3.0,
            ramp_start=t_w,
            ramp_duration=1.0,
            switch_time=switch,
        )

    @property
    def time(self) -> float:
        return self._steps * self.dt

    # ------------------------------------------------------------------ physics
    def model_parameters(self, model: str = "true") -> dict[str, float]:
        """Mass and drag of the "true" plant or of the "nominal" model (if it has one)."""
        check_choice("model", model, BARRIER_MODELS)
        if model == "true" or self.nominal_model == "exact":
            return {"mass": self.mass, "drag": self.drag}
        return {"mass": self.nominal_mass, "drag": self.nominal_drag}

    def _integrate(self, u: np.ndarray) -> None:
        """Exact zero-order-hold solution of m p'' = F u - c p' over dt."""
        k, dt = self.drag / self.mass, self.dt
        b = self.max_force * u / self.mass
        if k * dt < 1e-8:
            phi1, phi2, e = dt, 0.5 * dt * dt, 1.0 - k * dt
        else:
            e = np.exp(-k * dt)
            phi1 = -np.expm1(-k * dt) / k
            phi2 = (dt - phi1) / k
        self._p = self._p + self._v * phi1 + b * phi2
        self._v = self._v * e + b * phi1

    def set_state(self, position, velocity) -> None:
        """Set the point's position and velocity (copies) and recompute everything derived."""
        self._p = np.array(position, dtype=np.float64).reshape(self.dim)
        self._v = np.array(velocity, dtype=np.float64).reshape(self.dim)
        self._after_state_change()

    def set_time_step(self, steps: int) -> None:
        """Jump the scenario clock to ``steps`` control periods (tests, plotting)."""
        self._steps = int(steps)
        self._after_state_change()

    def _after_state_change(self) -> None:
        t = self.time
        self._obstacle_states = [ob.state(t) for ob in self.obstacles]
        self._ref_state = self.reference.state(t)
        self._invalidate_barriers()

    def _compute_barriers(self, kind: str) -> BarrierSet:
        po = np.array([s[0] for s in self._obstacle_states])
        vo = np.array([s[1] for s in self._obstacle_states])
        ao = np.array([s[2] for s in self._obstacle_states])
        radius = np.array([ob.radius for ob in self.obstacles]) + self.agent_radius
        d, vr = self._p - po, self._v - vo
        h, hd, n, curv = sphere_barriers(d, vr, radius)
        k = len(h)
        if kind == "zero":
            lf, lg = np.zeros(k), np.zeros((k, self.dim))
        elif kind == "kinematic":
            lf, lg = curv - np.einsum("ki,ki->k", n, ao), np.zeros((k, self.dim))
        else:
            params = self.model_parameters("true" if kind == "exact" else "nominal")
            drift = -params["drag"] / params["mass"] * self._v
            lf = n @ drift - np.einsum("ki,ki->k", n, ao) + curv
            lg = n * (self.max_force / params["mass"])
        q = np.broadcast_to(np.concatenate([self._p, self._v]), (k, 2 * self.dim))
        xi = np.concatenate([q, d, vr], axis=1)
        derivs = np.stack([h, hd], axis=1)
        for arr in (derivs, lf, lg, xi):
            arr.flags.writeable = False
        return BarrierSet(derivs, lf, lg, xi)

    def backup_action(self) -> np.ndarray:
        """Model-free brake for the safety filter's backup: ``u = -brake_gain p'`` (per m/s)
        saturated at the bounds; it opposes the velocity whatever the mass and drag."""
        return np.clip(-self.brake_gain * np.asarray(self._v, dtype=np.float64), -1.0, 1.0)

    # ------------------------------------------------------------------ gym API
    def _tracked_point(self) -> np.ndarray:
        return self._p

    def _contact(self) -> bool:
        return bool(self.barrier_values().min() < 0.0)

    def _get_obs(self) -> np.ndarray:
        states = self._obstacle_states
        r, rd, rdd = self._ref_state
        obs = np.concatenate(
            [self._p, self._v] + [s[0] for s in states] + [s[1] for s in states] + [r, rd, rdd]
        )
        return np.clip(obs, -self._obs_high, self._obs_high).astype(np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._steps = 0
        if self.scenario == "random":
            self._build_scenario(self.np_random)
        r, _, _ = self.reference.state(0.0)
        noise = self.np_random.uniform(-self.reset_noise, self.reset_noise, self.dim)
        self._p = r + noise
        self._v = np.zeros(self.dim)
        self._after_state_change()
        return self._get_obs(), self._reset_info()

    def _advance(self, u: np.ndarray) -> bool:
        self._integrate(u)
        self._steps += 1
        unstable = not (np.all(np.isfinite(self._p)) and np.all(np.isfinite(self._v)))
        if unstable:
            self._p = np.nan_to_num(self._p, nan=0.0, posinf=10.0, neginf=-10.0)
            self._v = np.zeros(self.dim)
        self._after_state_change()
        return unstable

    def _out_of_workspace(self) -> bool:
        return bool(np.max(np.abs(self._p)) > self.workspace_limit)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        c = Canvas(256, 1.0)
        for ob, (po, _, _) in zip(self.obstacles, self._obstacle_states, strict=True):
            c.disc(po, ob.radius, (220, 60, 60))
        r = self._ref_state[0]
        c.disc(r, 0.02, (40, 170, 40))
        c.disc(self._p, self.agent_radius, (40, 80, 220))
        return c.img.copy()
