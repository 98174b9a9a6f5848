"""The 1 kHz torque loop between a policy, the safety filter and a Franka behind libfranka.

Each tick (:meth:`Bridge.run`), between the robot's state and the command for the next
millisecond:

1. ``readOnce()``: the state ``q``, ``q'`` (a ``RobotState``) and the time that passed;
2. the robot's model at that state (``Model.mass``, ``Model.coriolis``) and the obstacle
   estimate of the perception callback;
3. the barrier terms (:class:`~afvsgp_gym.robots.terms.BarrierModel`);
4. the policy's torque, filtered by :meth:`SafetyController.filter` with the brake as its
   backup;
5. libfranka's torque-rate limiter (:func:`~afvsgp_gym.robots.libfranka.limit_rate`,
   1000 Nm/s) and ``writeOnce(Torques)``;
6. after the write, in the time left before the next state: ``SafetyController.observe``
   (learning) and the cost check (or its record, :class:`~afvsgp_gym.robots.simulated.CostLog`).

**Deadlines.** The steps from the read to the write have a budget (``budget``, 0.9 ms by
default). Python cannot pre-empt the filter, so the bridge checks twice: before the filter,
a step whose elapsed time plus the filter's expected time (a running mean of its recent
times, each capped at the budget) would overrun skips it; after it, a step that did overrun
discards its result. Either way the step is a *deadline miss* and writes the fallback: the
last safe action (the torque of the previous tick, when that tick was on time: the robot
holds a command for one period anyway) or else the brake.

**Safety stop.** A non-finite value anywhere (the state, the model, the obstacle estimate,
the terms, the policy's or the filter's torque) or a joint at its range stop or above its
speed in the measured state ends the run: the bridge writes the brake (rate limited, from the
last finite state; the last torque when there was none) with ``motion_finished = True`` and
returns the reason. An exception from the robot (libfranka's ``ControlException``: a reflex,
a limit, too many lost commands; ``NetworkException``) ends it too: the robot has already
stopped the motion, nothing more is written.

**Before the loop** (:meth:`Bridge.warm_up`) every computation runs 50 times on the robot's
state, without commanding anything (first calls allocate and fill caches), and the garbage
collector is off during the loop (its pauses reach milliseconds; the loop's garbage is freed
by reference counting).

**The brake** (:class:`Brake`) is the simulation's backup with the robot's own model:
``tau = c + M (-2 w q' - w^2 (q - q_hold))``, ``q_hold`` where it engaged (kept across short
runs of feasible ticks while the obstacles stand still); beyond the torque limits only the
largest share of the damping the limits admit (the hold point optionally kept while the arm
is near it).
"""

from __future__ import annotations

import gc
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, NamedTuple

import numpy as np

from afvsgp_gym.envs.braking import admissible_share
from afvsgp_gym.envs.joint_limits import FRANKA_MAX_TORQUE_RATE, JointLimits
from afvsgp_gym.robots.background_fit import BackgroundFit
from afvsgp_gym.robots.kinematics import END_EFFECTOR_OFFSET, SphereKinematics
from afvsgp_gym.robots.libfranka import CONTROL_PERIOD, TAU_MAX, as_matrix, limit_rate
from afvsgp_gym.robots.terms import FEATURE_DIM, BarrierModel, ObstacleEstimate
from afvsgp_gym.validation import check_real

__all__ = ["Brake", "Bridge", "BridgeReport", "Observation"]

_ZERO = np.zeros(1)

#: Step-time percentiles in the report.
PERCENTILES = (50.0, 90.0, 99.0, 99.9)


class Observation(NamedTuple):
    """What a policy sees each tick: time (s), joint angles and velocities, the robot's
    mass matrix (7, 7) and Coriolis vector (7,), the obstacle estimate and the
    end-effector point's ``(p (3,), v (3,), J (3, 7), J' q' (3,))`` (None: not computed)."""

    t: float
    q: np.ndarray
    dq: np.ndarray
    mass: np.ndarray
    coriolis: np.ndarray
    obstacles: ObstacleEstimate
    ee: tuple | None = None


class Brake:
    """Stop every joint and hold it with the robot's model (module docstring).

    Parameters
    ----------
    tau_max : array_like of shape (7,)
        Torque limits (Nm).
    frequency : float
        ``w`` (1/s), critically damped.
    memory : int
        Ticks without the brake (:meth:`release`) after which it engages anew; up to this
        many in a row it keeps its hold point while the obstacles stand still (default 100:
        0.1 s at 1 kHz, as the simulation's ``brake_hold_memory``; 0 takes a fresh hold
        point at every engagement). A hold point taken anew whenever the filter flips back
        to infeasible starts from the sagged pose each time, and the sag ratchets.
    slack : float
        rad (default 0, as the simulation's ``brake_hold_slack``): a saturated tick keeps
        the hold point while every joint is within this of it, and holds from where it is
        otherwise (0: at every saturated tick). Dropped at each saturated tick, the hold
        point can ratchet the sag the same way when the torque limits bind every few ticks.
    """

    #: m: see :meth:`see`.
    HOLD_WORLD_TOLERANCE = 1e-4

    def __init__(self, tau_max=TAU_MAX, frequency: float = 50.0, memory: int = 100,
                 slack: float = 0.0) -> None:
        self.tau_max = np.asarray(tau_max, dtype=np.float64)
        self.frequency = check_real(frequency, "frequency", low=0.0, low_open=True)
        self.memory = int(check_real(memory, "memory", low=0.0))
        self.slack = check_real(slack, "slack", low=0.0)
        self.hold: np.ndarray | None = None
        self._idle = 0
        self._world: np.ndarray | None = None  # the obstacle centres of this tick
        self._world_at_use: np.ndarray | None = None  # ... of the brake's last tick

    def release(self) -> None:
        """A tick without the brake: after more than ``memory`` in a row the next call engages
        anew (holds where it is then)."""
        self._idle += 1
        if self._idle > self.memory:
            self.hold = None

    def reset(self) -> None:
        """Forget the hold point: the next call engages anew."""
        self.hold, self._idle, self._world_at_use = None, 0, None

    def see(self, positions: np.ndarray) -> None:
        """The obstacle centres (O, 3) of this tick. An obstacle that moved more than
        ``HOLD_WORLD_TOLERANCE`` between the brake's last tick and its next engagement voids
        the kept hold point (the arm left it; the obstacle may be there now)."""
        self._world = np.asarray(positions, dtype=np.float64)

    def _world_moved(self) -> bool:
        a, b = self._world, self._world_at_use
        if a is None or b is None:
            return a is not b
        return a.shape != b.shape or bool(np.abs(a - b).max(initial=0.0)
                                          > self.HOLD_WORLD_TOLERANCE)

    def __call__(self, q: np.ndarray, dq: np.ndarray, mass: np.ndarray,
                 coriolis: np.ndarray) -> np.ndarray:
        if self.hold is not None and self._idle and self._world_moved():
            self.hold = None
        self._idle, self._world_at_use = 0, self._world
        w = self.frequency
        if self.hold is None:
            self.hold = q.copy()
        tau = coriolis + mass @ (-2.0 * w * dq - w * w * (q - self.hold))
        if np.all(np.abs(tau) <= self.tau_max):
            return tau
        if np.abs(q - self.hold).max() > self.slack:  # saturated: damping only, its
            self.hold = q.copy()  # largest admissible share; the hold point kept if near
        brake = mass @ (-2.0 * w * dq)
        share = admissible_share(coriolis, brake, self.tau_max)
        return np.clip(coriolis + share * brake, -self.tau_max, self.tau_max)


@dataclass
class BridgeReport:
    """What a run measured. Times in ms; ``cost_source`` says whether ``cost_steps`` counts
    the true state (a stand-in's ``cost``) or the measured one; ``deadline_misses`` counts
    the steps that wrote the fallback (``skipped_filters`` of them before the filter ran);
    ``late_reads`` the reads more than 1.5 periods after the last; ``lost_commands`` (a
    stand-in's) the ticks the robot went without a new command; ``min_h`` the smallest
    measured obstacle barrier (m); ``kinematics_error`` the start's check of the kinematics
    against the robot's own; ``barriers`` and ``self_collision_barriers`` the program's
    barriers (all of them, and the self-collision pairs among them); ``fit_ticks`` the ticks
    the learners' warm-up fit took in its own process (``fit_error`` its failure), None
    without one."""

    steps: int = 0
    seconds: float = 0.0
    rate_hz: float = 0.0
    deadline_misses: int = 0
    skipped_filters: int = 0
    cost_steps: int = 0
    cost_source: str = "measured"
    stop_reason: str = ""
    step_time_ms: dict[str, float] = field(default_factory=dict)
    observe_time_ms: dict[str, float] = field(default_factory=dict)
    filter_active_steps: int = 0
    filter_infeasible_steps: int = 0
    rate_limited_steps: int = 0
    late_reads: int = 0
    min_success_rate: float = 1.0
    min_h: float = math.inf
    lost_commands: int | None = None
    kinematics_error: dict[str, float] | None = None
    barriers: int = 0
    self_collision_barriers: int = 0
    fit_ticks: int | None = None
    fit_error: str | None = None

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["min_h"] = None if not math.isfinite(self.min_h) else self.min_h
        return out


def _percentiles(values: np.ndarray) -> dict[str, float]:
    if not len(values):
        return {}
    ms = values * 1e3
    out = {f"p{p:g}": float(np.percentile(ms, p)) for p in PERCENTILES}
    out["max"] = float(ms.max())
    out["mean"] = float(ms.mean())
    return out


def _finite(*arrays: np.ndarray) -> bool:
    """Every entry finite: one sum (NaN and inf propagate; finite values this large do not
    occur in a robot's state)."""
    total = 0.0
    for a in arrays:
        total += a.sum()
    return math.isfinite(total)


class _Stop(Exception):
    """A safety stop inside a step (its reason)."""


class Bridge:
    """The torque loop of one run (module docstring).

    Parameters
    ----------
    robot
        ``start_torque_control()`` (libfranka's ``Robot`` or a stand-in).
    model
        ``mass(state)``, ``coriolis(state)`` (libfranka's ``Model``).
    barriers : BarrierModel
        The barriers and the kinematics of this robot's angles.
    controller : SafetyController
        Built for ``barriers`` (``n_barriers``, ``layout``), actions in Nm.
    policy : callable
        ``policy(Observation) -> torque (7,)`` (Nm, on top of the gravity compensation).
    obstacles : callable
        ``obstacles(t) -> ObstacleEstimate`` (the perception callback; ``t``, like the
        policy's ``Observation.t``, is the time in s since the run's first state).
    limits : JointLimits
        The robot's joint ranges and speeds: the stop's check of the measured state.
    torques : callable
        The command type, ``torques(tau_list)`` (``pylibfranka.Torques``).
    budget : float
        s from the read to the write (default 0.9 ms).
    cost : callable, CostLog or None
        ``cost() -> bool`` of the true state after each tick (a stand-in's); an object with
        ``record()`` and ``count() -> int`` (a stand-in's
        :class:`~afvsgp_gym.robots.simulated.CostLog`): ``record()`` after each tick,
        ``count()`` after the run, so the check's time stays off the loop; None: the
        measured state's (some pair with ``h < 0``).
    learn : bool
        Call ``controller.observe`` after each write.
    background_fit : bool
        With ``learn``, fit the learners on the warm-up samples in a process of their own
        (:class:`~afvsgp_gym.robots.background_fit.BackgroundFit`; the default: the fit takes
        hundreds of ticks); False: in ``observe``, inside the loop (deterministic stepped runs).
    brake : Brake or None
    clock : callable
        Seconds (``time.perf_counter``).
    """

    def __init__(self, robot: Any, model: Any, barriers: BarrierModel, controller: Any,
                 policy: Callable[[Observation], np.ndarray],
                 obstacles: Callable[[float], ObstacleEstimate], limits: JointLimits,
                 torques: Callable[[list], Any], *, budget: float = 0.9e-3,
                 cost: Callable[[], bool] | Any | None = None, learn: bool = True,
                 background_fit: bool = True, brake: Brake | None = None,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        if not isinstance(barriers, BarrierModel):
            raise ValueError(f"barriers must be a BarrierModel. Got: {barriers!r}")
        if controller.n_barriers != barriers.n_barriers:
            raise ValueError(f"controller has {controller.n_barriers} barriers, barriers "
                             f"{barriers.n_barriers}")
        if not isinstance(limits, JointLimits):
            raise ValueError(f"limits must be a JointLimits. Got: {limits!r}")
        self.robot, self.model, self.barriers = robot, model, barriers
        self.controller, self.policy, self.obstacles = controller, policy, obstacles
        self.limits, self.torques = limits, torques
        self.budget = check_real(budget, "budget", low=0.0, low_open=True)
        self.cost, self.learn = cost, bool(learn)
        self.background_fit = bool(background_fit)
        self._fit_sent = 0  # the step the warm-up samples went to the fitting process
        #: ``cost`` records in the loop and counts after it (a CostLog)
        self._cost_deferred = callable(getattr(cost, "record", None)) and callable(
            getattr(cost, "count", None))
        if cost is not None and not (self._cost_deferred or callable(cost)):
            raise ValueError(f"cost must be a callable, an object with record() and count() "
                             f"or None. Got: {cost!r}")
        self.brake = Brake() if brake is None else brake
        self.clock = clock
        #: The kinematics check's figures, reported (``build_bridge`` sets them).
        self.kinematics_error: dict[str, float] | None = None
        kin = barriers.kinematics  # the spheres and the end-effector point in one pass
        self._kinematics = SphereKinematics(kin.chain, [*kin.links, 7],
                                            np.vstack([kin.offsets, END_EFFECTOR_OFFSET]),
                                            backend=kin.backend)
        self._filter_time = 0.0  # running mean of the filter's time (s)

    # ------------------------------------------------------------------ one tick
    def _violation(self, q: np.ndarray, dq: np.ndarray) -> str | None:
        """Which joint is at its range stop or above its speed (None: none)."""
        lim = self.limits
        if not lim.violation(q, dq):
            return None
        for j in range(lim.n_joints):
            if q[j] <= lim.lower[j] or q[j] >= lim.upper[j]:
                return f"joint{j + 1} at its range stop (q = {q[j]:.4f} rad)"
            if abs(dq[j]) > lim.max_speed[j]:
                return f"joint{j + 1} above its speed (dq = {dq[j]:.4f} rad/s)"
        return None

    def _measure(self, state: Any, t: float) -> tuple:
        """The state, model, obstacles and terms of a tick; :class:`_Stop` on a non-finite
        value or a limit violation."""
        q = np.asarray(state.q, dtype=np.float64)
        dq = np.asarray(state.dq, dtype=np.float64)
        if not _finite(q, dq):
            raise _Stop("non_finite: state")
        where = self._violation(q, dq)
        if where is not None:
            raise _Stop(f"limit_violation: {where}")
        mass = as_matrix(self.model.mass(state), 7, 7)
        coriolis = np.asarray(self.model.coriolis(state), dtype=np.float64)
        if not _finite(mass, coriolis):
            raise _Stop("non_finite: model")
        self._last_finite = (q, dq, mass, coriolis)
        est = self.obstacles(t)
        if not _finite(est.position, est.velocity, est.acceleration,
                       _ZERO if est.covariance is None else est.covariance):
            raise _Stop("non_finite: obstacles")
        self.brake.see(est.position)
        p, v, jac, acc = self._kinematics(q, dq)
        try:
            terms = self.barriers.terms(q, dq, mass, coriolis, est,
                                        (p[:-1], v[:-1], jac[:-1], acc[:-1]))
        except np.linalg.LinAlgError:
            raise _Stop("non_finite: model (singular mass matrix)") from None
        if not _finite(terms.derivatives, terms.lf, terms.lg, terms.xi,
                       _ZERO if terms.covariance is None else terms.covariance):
            raise _Stop("non_finite: terms")
        return q, dq, mass, coriolis, est, terms, (p[-1], v[-1], jac[-1], acc[-1])

    def _fallback(self, q, dq, mass, coriolis) -> np.ndarray:
        """The last safe action when the previous tick was on time, else the brake."""
        if self._on_time and self._last_tau is not None:
            return self._last_tau
        return self.brake(q, dq, mass, coriolis)

    def _step(self, state: Any, t: float, t0: float) -> tuple[np.ndarray, bool, Any]:
        """``(torque before the rate limiter, on time, terms)`` of one tick."""
        q, dq, mass, coriolis, est, terms, ee = self._measure(state, t)
        u_nom = np.asarray(self.policy(Observation(t, q, dq, mass, coriolis, est, ee)),
                           dtype=np.float64)
        if u_nom.shape != (7,) or not _finite(u_nom):
            raise _Stop("non_finite: policy")
        if self.clock() - t0 + self._filter_time > self.budget:
            self._filter_time *= 0.9  # a skip must not lock the filter out
            self.report.skipped_filters += 1
            return self._fallback(q, dq, mass, coriolis), False, terms
        t1 = self.clock()
        res = self.controller.filter(
            u_nom, terms, u_backup=lambda: self.brake(q, dq, mass, coriolis))
        t2 = self.clock()
        # a running mean of the filter's time, each sample capped at the budget (one stall
        # must not make the following steps skip the filter)
        self._filter_time += 0.05 * (min(t2 - t1, self.budget) - self._filter_time)
        if not _finite(res.u):
            raise _Stop("non_finite: action")
        if t2 - t0 > self.budget:
            return self._fallback(q, dq, mass, coriolis), False, terms
        if res.active:
            self.report.filter_active_steps += 1
        if not res.feasible:
            self.report.filter_infeasible_steps += 1
        if not res.status.startswith("backup"):  # (else the brake engaged inside the filter)
            self.brake.release()
        return res.u, True, terms

    def _stop_torque(self) -> np.ndarray:
        """The stop's command: the brake from the last finite state, rate limited from the
        last command (that command itself when no state was finite)."""
        last = np.zeros(7) if self._last_tau is None else self._last_tau
        if self._last_finite is None:
            return last
        return limit_rate(self.brake(*self._last_finite), last)

    def _finish(self, control: Any, tau: np.ndarray) -> str:
        """Write ``tau`` with ``motion_finished``; "" or what went wrong."""
        cmd = self.torques(np.asarray(tau, dtype=np.float64).tolist())
        cmd.motion_finished = True
        try:
            control.writeOnce(cmd)
        except (RuntimeError, OSError, ValueError) as exc:
            return f" (the final command failed: {exc})"
        return ""

    def _advance_fit(self, fitter: BackgroundFit) -> None:
        """After a write: send the warm-up samples to the fitting process once they are
        in; install the fitted learners once they are back (``fit_ticks`` later)."""
        ctrl, rep = self.controller, self.report
        try:
            if not fitter.pending and ctrl.warmup_complete and fitter.error is None:
                fitter.submit(ctrl)
                self._fit_sent = rep.steps
            if fitter.pending:
                bank = fitter.poll()
                if bank is not None:
                    ctrl.install_fitted(bank)
                    rep.fit_ticks = rep.steps - self._fit_sent
        except Exception as exc:  # a lost worker: the loop goes on, the learners unfitted
            fitter.pending = False
            fitter.error = f"{type(exc).__name__}: {exc}"
        if fitter.error is not None:
            rep.fit_error = fitter.error

    # ------------------------------------------------------------------ the run
    def warm_up(self, steps: int = 50) -> None:
        """Run the tick's computations ``steps`` times on the robot's current state
        (``read_once``) without commanding anything: the first calls of the numerical code
        pay for allocations and caches, which must not happen inside the 1 kHz loop. A stop
        condition of that state raises ``RuntimeError`` with its reason (nothing starts)."""
        state = self.robot.read_once()
        t = 0.0
        self._last_tau, self._last_finite, self._on_time = np.zeros(7), None, False
        self.report = BridgeReport()
        for _ in range(int(steps)):
            try:
                self._step(state, t, self.clock())
            except _Stop as stop:
                raise RuntimeError(f"the robot's state stops the bridge: {stop}") from None
        self.brake.reset()
        self._filter_time = 0.0

    def run(self, seconds: float, warm_up: int = 50) -> BridgeReport:
        """Run the loop for ``seconds`` of robot time (or until a stop), after
        :meth:`warm_up` (``warm_up`` steps); the report."""
        seconds = check_real(seconds, "seconds", low=0.0, low_open=True)
        if warm_up:
            self.warm_up(warm_up)
        n_max = int(round(seconds / CONTROL_PERIOD))
        model = self.barriers
        self.report = rep = BridgeReport(cost_source="measured" if self.cost is None
                                         else "true_state",
                                         kinematics_error=self.kinematics_error,
                                         barriers=model.n_barriers,
                                         self_collision_barriers=model.n_pair_rows
                                         - model.n_pairs)
        step_times = np.empty(n_max)
        observe_times = np.empty(n_max)
        self._last_tau, self._last_finite, self._on_time = None, None, False
        prev: tuple | None = None  # (terms, torque) of the previous tick, for observe
        t_first = None
        k_pairs = self.barriers.n_pairs
        ctrl, fitter = self.controller, None
        if self.learn and self.background_fit and ctrl.warming_up:
            # (a second or so, before the robot's clock starts; the samples' block too)
            fitter = BackgroundFit().start(ctrl.warmup_shapes(ctrl.config.warmup_samples,
                                                              FEATURE_DIM))
            ctrl.fit_at_warmup = False
        gc_was_enabled = gc.isenabled()
        gc.collect()
        gc.disable()  # no collector pauses inside the loop (its garbage is freed by refcount)
        control = self.robot.start_torque_control()
        start = self.clock()
        reason = "completed"
        try:
            while rep.steps < n_max:
                try:
                    state, period = control.readOnce()
                except (RuntimeError, OSError) as exc:  # ControlException, NetworkException
                    reason = f"robot_error: {exc}"
                    break
                t0 = self.clock()
                # the robot's last command received (libfranka's limitRate takes
                # tau_J_d): after a lost command the next one steps from what the robot
                # holds, not from what was sent
                received = np.asarray(getattr(state, "tau_J_d", ()), dtype=np.float64)
                if received.shape == (7,) and _finite(received):
                    self._last_tau = received.copy()
                elif self._last_tau is None:
                    self._last_tau = np.zeros(7)
                dt = float(period.to_sec())  # 0 at the first read
                if dt > 1.5 * CONTROL_PERIOD:
                    rep.late_reads += 1
                rate = getattr(state, "control_command_success_rate", 1.0)
                rep.min_success_rate = min(rep.min_success_rate, float(rate))
                if t_first is None:  # the robot's clock counts from its start
                    t_first = float(state.time.to_sec())
                t = float(state.time.to_sec()) - t_first
                try:
                    u, on_time, terms = self._step(state, t, t0)
                except _Stop as stop:
                    reason = str(stop)
                    reason += self._finish(control, self._stop_torque())
                    break
                tau = limit_rate(u, self._last_tau, FRANKA_MAX_TORQUE_RATE, CONTROL_PERIOD)
                if not np.array_equal(tau, u):
                    rep.rate_limited_steps += 1
                try:
                    control.writeOnce(self.torques(tau.tolist()))
                except (RuntimeError, OSError) as exc:
                    reason = f"robot_error: {exc}"
                    break
                step_times[rep.steps] = self.clock() - t0
                if not on_time:
                    rep.deadline_misses += 1
                self._last_tau, self._on_time = tau, on_time
                # after the write: learning and the cost check
                t3 = self.clock()
                if self.learn and prev is not None and dt > 0:
                    ctrl.observe(prev[0], prev[1], terms, dt)
                if fitter is not None:
                    self._advance_fit(fitter)
                prev = (terms, tau)
                observe_times[rep.steps] = self.clock() - t3
                h = float(terms.h[:k_pairs].min()) if k_pairs else math.inf
                rep.min_h = min(rep.min_h, h)
                if self._cost_deferred:
                    self.cost.record()
                else:
                    bad = self.cost() if self.cost is not None else h < 0.0
                    rep.cost_steps += int(bool(bad))
                rep.steps += 1
        except KeyboardInterrupt:
            reason = "interrupted" + self._finish(control, self._stop_torque())
        else:
            if reason == "completed":
                reason += self._finish(control, np.zeros(7) if self._last_tau is None
                                       else self._last_tau)
        finally:
            if gc_was_enabled:
                gc.enable()
            if fitter is not None:
                fitter.close()
                ctrl.fit_at_warmup = True
        rep.seconds = self.clock() - start
        if self._cost_deferred:  # the true states of the run, checked now
            rep.cost_steps = int(self.cost.count())
        rep.rate_hz = rep.steps / rep.seconds if rep.seconds > 0 else 0.0
        rep.stop_reason = reason
        rep.step_time_ms = _percentiles(step_times[: rep.steps])
        rep.observe_time_ms = _percentiles(observe_times[: rep.steps])
        return rep
