"""The bridge's loop on the MuJoCo stand-in: a run, the rate limiter, the deadline path (an
injected slow step gets the last safe action, a second one the brake) and the stop paths (a
NaN state, a limit violation, the robot's reflex, a NaN policy)."""

import mujoco
import numpy as np
import pytest

from afvsgp_gym.envs.safety_spheres import sphere_arrays
from afvsgp_gym.envs.scenario import ObstacleSpec
from afvsgp_gym.robots.bridge import Brake, Observation
from afvsgp_gym.robots.kinematics import GYMNASIUM_PANDA, SphereKinematics
from afvsgp_gym.robots.libfranka import as_matrix, limit_rate
from afvsgp_gym.robots.policies import make_robot_policy
from afvsgp_gym.robots.run import build_bridge, make_controller
from afvsgp_gym.robots.simulated import SimulatedFranka, Torques
from afvsgp_gym.robots.terms import BarrierModel

DT = 1e-3
#: A table at the mount (z = 0), the envs' obstacles= dict.
TABLE = {"type": "plane", "position": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]}


class Recording:
    """The stand-in behind the bridge, recording the states read and the commands written;
    ``on_read(tick, robot)`` may change the plant before a tick is read, ``on_state(tick,
    state)`` the state as it arrives (a corrupted packet)."""

    def __init__(self, robot, on_read=None, on_state=None):
        self.robot, self.on_read, self.on_state = robot, on_read, on_state
        self.states, self.commands = [], []

    def start_torque_control(self):
        self.control = self.robot.start_torque_control()
        return self

    def readOnce(self):  # noqa: N802 (libfranka's name)
        if self.on_read is not None:
            self.on_read(len(self.states), self.robot)
        state, period = self.control.readOnce()
        if self.on_state is not None:
            self.on_state(len(self.states), state)
        self.states.append(state)
        return state, period

    def writeOnce(self, command):  # noqa: N802
        self.commands.append((np.array(command.tau_J), bool(command.motion_finished)))
        self.control.writeOnce(command)

    def read_once(self):
        return self.robot.read_once()


class FakeClock:
    """Time that passes only when a test says so (no wall-clock timing in the tests)."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def bridge_model(robot):
    kin = SphereKinematics.from_spheres(robot.kinematics, robot.spheres)
    return BarrierModel(kin, sphere_arrays(robot.spheres)[2], [0.05], robot.joint_limits)


def _bridge(robot=None, agent="hold", budget=0.9e-3, on_read=None, on_state=None,
            torque_error=(3, 3, 3, 3, 1, 1, 1), learner="none", cost=None,
            background_fit=False, filter_kwargs=None, self_collision=False, **kwargs):
    robot = SimulatedFranka(realtime=False, **kwargs) if robot is None else robot
    rec = Recording(robot, on_read, on_state)
    bridge = build_bridge(rec, robot.load_model(), Torques, chain=robot.kinematics,
                          obstacle_radii=[o.radius for o in robot.obstacles],
                          obstacles=robot.obstacle_estimate, limits=robot.joint_limits,
                          agent=agent, spheres=robot.spheres, budget=budget,
                          cost=robot.cost if cost is None else cost(robot),
                          torque_error=torque_error, learner=learner,
                          obstacle_shapes=[o.shape for o in robot.obstacles],
                          background_fit=background_fit, filter_kwargs=filter_kwargs,
                          self_collision=self_collision)
    bridge.clock = FakeClock()
    return bridge, rec, robot


def test_a_run_completes_and_every_command_respects_the_rate_limit():
    bridge, rec, robot = _bridge(agent="nominal")
    report = bridge.run(0.3)
    assert report.stop_reason == "completed"
    assert report.steps == 300 and report.deadline_misses == 0 and report.cost_steps == 0
    taus = np.array([c[0] for c in rec.commands])
    assert np.abs(np.diff(taus, axis=0)).max() <= 1000.0 * DT * (1 + 1e-12)
    assert rec.commands[-1][1] and not any(c[1] for c in rec.commands[:-1])
    assert robot.lost_commands == 0


def test_the_rate_limiter_is_libfrankas():
    last = np.zeros(7)
    tau = np.array([5.0, -5.0, 0.5, -0.5, 1.0, -1.0, 0.0])
    np.testing.assert_array_equal(limit_rate(tau, last),
                                  [1.0, -1.0, 0.5, -0.5, 1.0, -1.0, 0.0])


def test_a_torque_step_is_rate_limited_so_the_robot_does_not_abort():
    bridge, rec, _ = _bridge(agent="zero")
    bridge.policy = lambda obs: np.full(7, 10.0) * (obs.t > 0.05)
    report = bridge.run(0.1)
    assert report.stop_reason == "completed" and report.rate_limited_steps >= 9


def test_after_a_lost_command_the_next_steps_from_what_the_robot_holds():
    """A command lost on the way (the robot holds the previous one): the next is rate
    limited from the state's ``tau_J_d``, the command the robot received last (libfranka's
    ``limitRate``), so a torque ramp goes on without the robot's torque-step reflex."""
    bridge, rec, robot = _bridge(agent="zero")
    bridge.policy = lambda obs: np.full(7, 10.0) * (obs.t > 0.02)

    def lose(tick, _robot):
        if tick == 25:  # the command written after the 24th read never arrives
            rec.control._written = None
    rec.on_read = lose
    report = bridge.run(0.06)
    assert report.stop_reason == "completed" and robot.lost_commands == 1
    for state, (tau, _) in zip(rec.states, rec.commands[:-1], strict=True):  # (-1: finish)
        assert np.abs(tau - np.asarray(state.tau_J_d)).max() <= 1000.0 * DT * (1 + 1e-12)
    held = rec.states[25].tau_J_d  # the robot holds the command before the lost one
    np.testing.assert_array_equal(held, rec.commands[23][0])
    assert not np.array_equal(rec.commands[25][0], rec.commands[24][0] + 1.0)


def _slow_policy(bridge, ticks, seconds=0.05):
    """The policy takes ``seconds`` (fake clock) at the given robot ticks."""
    inner = bridge.policy

    def policy(obs):
        if round(obs.t / DT) in ticks and bridge.report.steps:  # not during the warm-up
            bridge.clock.now += seconds
        return inner(obs)

    return policy


def test_a_slow_step_writes_the_last_safe_action_a_second_one_the_brake():
    bridge, rec, robot = _bridge(agent="nominal")
    bridge.policy = _slow_policy(bridge, {100, 101})
    report = bridge.run(0.2)
    assert report.stop_reason == "completed"
    assert report.deadline_misses == 2 and report.skipped_filters == 2
    # tick k's command follows the state read at tick k (the first read is tick 0)
    k = next(i for i, s in enumerate(rec.states) if round(s.time.to_sec() / DT) == 100)
    taus = [c[0] for c in rec.commands]
    np.testing.assert_array_equal(taus[k], taus[k - 1])  # the last safe action, held
    state = rec.states[k + 1]  # the second: the brake from that state, rate limited
    model = robot.load_model()
    brake = Brake()(np.asarray(state.q), np.asarray(state.dq),
                    as_matrix(model.mass(state), 7, 7), np.asarray(model.coriolis(state)))
    np.testing.assert_allclose(taus[k + 1], limit_rate(brake, taus[k]), rtol=0, atol=1e-12)


def test_a_step_that_overruns_in_the_filter_is_discarded():
    bridge, rec, _ = _bridge(agent="nominal")
    inner = bridge.controller.filter
    calls = []

    def slow_filter(*args, **kwargs):
        res = inner(*args, **kwargs)
        calls.append(1)
        if len(calls) == 150:  # inside the run (the warm-up made 50 calls)
            bridge.clock.now += 0.05
        return res

    bridge.controller.filter = slow_filter
    report = bridge.run(0.2)
    assert report.deadline_misses == 1 and report.skipped_filters == 0
    taus = [c[0] for c in rec.commands]
    k = 99  # the 100th step of the run
    np.testing.assert_array_equal(taus[k], taus[k - 1])


def test_a_nan_state_stops_with_the_brake():
    def corrupt(tick, state):
        if tick == 50:
            state.dq[2] = np.nan

    bridge, rec, _ = _bridge(on_state=corrupt)
    report = bridge.run(0.2)
    assert report.stop_reason == "non_finite: state"
    tau, finished = rec.commands[-1]
    assert finished and np.isfinite(tau).all()
    assert report.steps == 50


def test_a_limit_violation_stops_the_run_with_its_joint():
    def push(tick, robot):
        if tick == 30:
            dq = robot.data.qvel[:7].copy()
            dq[3] = 2.3  # joint 4's datasheet speed is 2.175 rad/s
            robot.set_state(robot.data.qpos[:7], dq)

    bridge, rec, _ = _bridge(on_read=push, reflex=False)
    report = bridge.run(0.2)
    assert report.stop_reason.startswith("limit_violation: joint4 above its speed")
    assert rec.commands[-1][1]


def test_the_robots_reflex_ends_the_run():
    def push(tick, robot):
        if tick == 30:
            q = robot.data.qpos[:7].copy()
            q[0] = robot.joint_limits.upper[0] + 0.01  # past joint 1's range stop
            robot.set_state(q, robot.data.qvel[:7])

    bridge, rec, _ = _bridge(on_read=push)
    report = bridge.run(0.2)
    assert report.stop_reason.startswith("robot_error:")
    assert "joint_position_limits_violation" in report.stop_reason
    assert not rec.commands[-1][1]  # the robot aborted: nothing more written


def test_a_nan_policy_stops():
    bridge, rec, _ = _bridge(agent="zero")
    bridge.policy = lambda obs: np.full(7, np.nan) if obs.t > 0.02 else np.zeros(7)
    report = bridge.run(0.1)
    assert report.stop_reason == "non_finite: policy" and rec.commands[-1][1]


def test_the_stand_ins_model_has_libfrankas_shapes_and_the_kinematics_jacobian():
    robot = SimulatedFranka(realtime=False)
    model = robot.load_model()
    state = robot.read_once()
    state.q = state.q + np.linspace(-0.3, 0.3, 7)
    mass = model.mass(state)
    assert len(mass) == 49 and len(model.coriolis(state)) == 7
    assert len(model.gravity(state)) == 7
    m = as_matrix(mass, 7, 7)
    np.testing.assert_allclose(m, m.T, atol=1e-12)
    jac = as_matrix(model.zero_jacobian(state), 6, 7)
    ee = SphereKinematics(GYMNASIUM_PANDA, [7], [(0.0, 0.0, 0.21)])
    np.testing.assert_allclose(jac[:3], ee(state.q, np.zeros(7))[2][0], rtol=0, atol=1e-9)


def test_a_learner_observes_every_step_after_the_write():
    bridge, rec, _ = _bridge(agent="hold")
    seen = []
    inner = bridge.controller.observe
    bridge.controller.observe = lambda *a: seen.append(a) or inner(*a)
    bridge.learn = True
    report = bridge.run(0.05)
    assert report.stop_reason == "completed" and len(seen) == report.steps - 1
    terms_before, tau, terms_after, dt = seen[10]
    np.testing.assert_array_equal(tau, rec.commands[10][0])  # the torque as written
    assert dt == pytest.approx(DT) and terms_before is seen[9][2]


def test_the_shared_learner_runs_on_the_robots_own_model():
    """``learner="afvsgp-shared"`` on the bridge: after the warm-up the seven joint learners
    predict the band of the pairs in the program through the terms' projection (n' J_s, the
    robot's kinematics). A static sphere 12 cm beside the held fingertip (4 cm from the
    nearest safety sphere) brings its pairs into the program."""
    probe = SimulatedFranka(realtime=False)
    q0 = np.asarray(probe.read_once().q, dtype=np.float64)
    tip = SphereKinematics.from_spheres(probe.kinematics, probe.spheres).positions(q0)[-1]
    robot = SimulatedFranka([ObstacleSpec(tip + [0.0, 0.12, 0.0], 0.05)], realtime=False)
    bridge, _, _ = _bridge(robot, agent="hold", learner="afvsgp-shared")
    ctrl, k = bridge.controller, bridge.barriers.n_pair_rows  # obstacle and self pairs
    results = []
    inner = ctrl.filter
    ctrl.filter = lambda u, terms, **kw: results.append(r := inner(u, terms, **kw)) or r
    report = bridge.run(0.8)
    assert report.stop_reason == "completed" and report.cost_steps == 0
    assert not ctrl.warming_up and ctrl.layout.projected.sum() == k
    std = np.array([r.delta_b_std[:k] for r in results if not r.warmup])
    assert np.isfinite(std).any(axis=1).sum() > 100  # steps with pairs in the program
    assert (std[np.isfinite(std)] > 0).all()


def test_a_noisy_camera_gives_estimates_with_covariance_to_the_filter():
    robot = SimulatedFranka(realtime=False, obstacle_noise=0.01, seed=3)
    bridge, _, _ = _bridge(robot, agent="nominal")
    seen = []
    inner = bridge.controller.filter
    bridge.controller.filter = lambda u, terms, **k: seen.append(terms) or inner(u, terms, **k)
    report = bridge.run(0.1)
    assert report.stop_reason == "completed"
    cov = seen[-1].covariance
    k = bridge.barriers.n_pairs
    assert cov is not None and np.all(cov[:k, 0, 0] > 0) and not cov[k:].any()
    est, true = robot.obstacle_estimate(), robot.true_obstacles()
    assert 0 < np.abs(est.position - true.position).max() < 0.05


def test_a_noisy_camera_on_a_box_gives_its_pairs_a_covariance_and_the_table_none():
    """The camera senses the box's centre (the Kalman estimate and its covariance, through
    shape_pair_covariance to every pair of the box); the table, a plane, is given exactly
    (covariance 0), as are the joint limits."""
    robot = SimulatedFranka([TABLE, {**BOX, "position": [0.45, 0.3, 0.3]}], realtime=False,
                            obstacle_noise=0.01, seed=3)
    bridge, _, _ = _bridge(robot, agent="nominal")
    seen = []
    inner = bridge.controller.filter
    bridge.controller.filter = lambda u, terms, **k: seen.append(terms) or inner(u, terms, **k)
    report = bridge.run(0.1)
    assert report.stop_reason == "completed" and report.cost_steps == 0
    cov, s = seen[-1].covariance, len(robot.spheres)
    assert cov is not None and not cov[:s].any() and not cov[2 * s:].any()
    assert np.all(cov[s:2 * s, 0, 0] > 0)
    est, true = robot.obstacle_estimate(), robot.true_obstacles()
    np.testing.assert_array_equal(est.position[0], true.position[0])
    assert not est.covariance[0].any() and 0 < np.abs(est.position[1] - true.position[1]).max()


def test_bad_arguments_name_the_argument():
    robot = SimulatedFranka(realtime=False)
    with pytest.raises(ValueError, match="learner 'oracle'"):
        make_controller(bridge_model(robot), "oracle")
    with pytest.raises(ValueError, match="payload_mass"):
        SimulatedFranka(payload_mass=-1.0)
    with pytest.raises(ValueError, match="budget"):
        _bridge(robot, budget=0.0)
    for entry, message in (
            ({"type": "cone", "position": [0.5, 0, 0.4]}, r"obstacles\[1\]\['type'\]"),
            ({"type": "box", "position": [0.5, 0, 0.4], "half_sizes": [0.05, 0.0, 0.05]},
             r"obstacles\[1\]\['half_sizes'\] must be > 0"),
            ({"type": "capsule", "position": [0.5, 0, 0.4], "radius": -0.02,
              "half_length": 0.1}, r"obstacles\[1\]\['radius'\] must be > 0"),
            ({"type": "plane", "position": [0, 0, np.nan], "normal": [0, 0, 1]},
             r"obstacles\[1\]\['position'\] must be finite"),
            ({"type": "plane", "position": [0, 0, 0], "normal": [0, 0, 1],
              "start": [0, 0, 1]}, r"obstacles\[1\]\['start'\]: a plane is static")):
        with pytest.raises(ValueError, match=message):
            SimulatedFranka(obstacles=[TABLE, entry], realtime=False)


@pytest.mark.parametrize("bound, safe", [([3, 3, 3, 3, 1, 1, 1], True), (0.0, False)])
def test_the_bound_keeps_the_undeclared_payload_out_of_the_moving_sphere(bound, safe):
    """The whole loop through the obstacle's arrival (stepped without the wall clock, on
    the fake clock: no step falls back, the run is deterministic): with the torque-error
    bound no step has cost while the filter acts; without it the 1 kg payload the model does
    not know takes the hand into the sphere (the test can fail)."""
    bridge, _, _ = _bridge(agent="nominal", torque_error=bound)
    report = bridge.run(10.0)
    assert report.stop_reason == "completed" and report.filter_active_steps > 500
    assert (report.cost_steps == 0) == safe
    assert report.min_h < 0.05


def test_the_cost_log_counts_after_the_run_what_the_check_in_the_loop_counts():
    """``robot --simulate`` records the true states in the loop and checks them after it
    (:class:`CostLog`): the same count and clearance as the check at each tick, on a run
    whose undeclared payload takes the hand into the sphere (bound 0)."""
    closest = [np.inf]

    def checked(robot):
        def cost():
            closest[0] = min(closest[0], float(robot.clearance().min()))
            return robot.cost()
        return cost

    in_loop = _bridge(agent="nominal", torque_error=0.0, cost=checked)[0].run(10.0)
    bridge, _, robot = _bridge(agent="nominal", torque_error=0.0,
                               cost=SimulatedFranka.cost_log)
    deferred = bridge.run(10.0)
    assert deferred.steps == in_loop.steps == len(bridge.cost) == 10000
    assert deferred.cost_steps == in_loop.cost_steps > 0
    assert bridge.cost.min_clearance == closest[0] < 0.0
    assert deferred.cost_source == in_loop.cost_source == "true_state"
    # the replay leaves the plant as it was (and counts alike again)
    ticks, qpos, data = robot.ticks, robot.data.qpos.copy(), robot.data
    assert bridge.cost.count() == deferred.cost_steps
    assert robot.ticks == ticks and robot.data is data
    np.testing.assert_array_equal(robot.data.qpos, qpos)
    with pytest.raises(ValueError, match="cost must be"):
        _bridge(cost=lambda robot: 3.0)


def test_the_brake_keeps_its_hold_point_across_short_feasible_gaps():
    """Up to ``memory`` ticks without the brake keep its hold point (a flipping filter must
    not ratchet the sag); one more, or ``reset``, and it engages where the arm is then."""
    mass, coriolis, dq = np.eye(7), np.zeros(7), np.zeros(7)
    q0, q1 = np.zeros(7), np.full(7, 0.001)  # within the torque limits
    brake = Brake(memory=3)
    brake(q0, dq, mass, coriolis)
    for _ in range(3):
        brake.release()
    tau = brake(q1, dq, mass, coriolis)  # pulled back to q0
    np.testing.assert_allclose(tau, -brake.frequency ** 2 * (q1 - q0), rtol=1e-12)
    for _ in range(4):
        brake.release()
    np.testing.assert_array_equal(brake(q1, dq, mass, coriolis), np.zeros(7))  # anew at q1
    brake.reset()
    np.testing.assert_array_equal(brake(q0, dq, mass, coriolis), np.zeros(7))
    with pytest.raises(ValueError, match="memory"):
        Brake(memory=-1)


def test_a_saturated_brake_keeps_its_hold_point_within_its_slack():
    """A saturated tick keeps the hold point while every joint is within ``slack`` of it
    (the damping share only, no spring), and holds from where the arm is beyond it."""
    mass, coriolis, tau_max = np.eye(7), np.zeros(7), np.full(7, 100.0)
    q0, fast = np.zeros(7), np.full(7, 2.0)  # 2 w |q'| = 200 Nm: saturated
    brake = Brake(tau_max=tau_max, slack=0.02)
    brake(q0, np.zeros(7), mass, coriolis)
    tau = brake(q0 + 0.01, fast, mass, coriolis)
    np.testing.assert_allclose(tau, -tau_max, rtol=1e-12)  # the largest share of damping
    np.testing.assert_array_equal(brake.hold, q0)  # kept
    np.testing.assert_allclose(brake(q0 + 0.01, np.zeros(7), mass, coriolis),
                               -brake.frequency ** 2 * 0.01 * np.ones(7), rtol=1e-9)
    brake(q0 + 0.03, fast, mass, coriolis)
    np.testing.assert_array_equal(brake.hold, q0 + 0.03)  # beyond the slack: anew
    fresh = Brake(tau_max=tau_max, slack=0.0)
    fresh(q0, np.zeros(7), mass, coriolis)
    fresh(q0 + 0.01, fast, mass, coriolis)
    np.testing.assert_array_equal(fresh.hold, q0 + 0.01)
    with pytest.raises(ValueError, match="slack"):
        Brake(slack=-0.1)


def test_the_brake_forgets_its_hold_point_when_an_obstacle_moved():
    """An obstacle that moved between the brake's last tick and its next engagement voids
    the kept hold point: the arm left it, the obstacle may be there now."""
    mass, coriolis, dq = np.eye(7), np.zeros(7), np.zeros(7)
    q0, q1 = np.zeros(7), np.full(7, 0.001)
    still, moving = np.zeros((1, 3)), np.array([[0.0, 0.0, 0.01]])
    brake = Brake(memory=3)
    brake.see(still)
    brake(q0, dq, mass, coriolis)
    brake.release()
    brake.see(still)  # the world stood still: the hold point is kept
    assert np.abs(brake(q1, dq, mass, coriolis)).max() > 0.0
    brake.release()
    brake.see(moving)  # it moved: the brake holds where the arm is
    np.testing.assert_array_equal(brake(q1, dq, mass, coriolis), np.zeros(7))
    brake.see(moving + 0.05)  # while engaged, a moving world keeps the hold point
    np.testing.assert_array_equal(brake(q0, dq, mass, coriolis),
                                  -brake.frequency ** 2 * (q0 - q1))


#: A low start: the end-effector 6 cm above a table at the mount and the hand's lowest
#: safety sphere 1 cm above it; the tracker's reference sweeps +-0.28 m along y there.
LOW_Q0 = (0.0, 0.4023, 0.0, -2.2773, 0.0, 0.5457, 0.785)
#: A box standing on the table across the sweep's -y half (reached about 2.7 s in).
BOX = {"type": "box", "position": [0.41, -0.2, 0.05], "half_sizes": [0.04, 0.03, 0.05],
       "quat": [np.cos(0.15), 0.0, 0.0, np.sin(0.15)]}


def _hits_without_the_filter(robot, seconds):
    """The obstacles (indices) the nominal policy's torque, rate limited but unfiltered,
    takes a safety sphere into, and the steps with cost, over ``seconds`` of the stand-in."""
    model = robot.load_model()
    policy = make_robot_policy("nominal", robot.kinematics, robot.read_once().q)
    control = robot.start_torque_control()
    state, _ = control.readOnce()
    last, hit, cost = np.zeros(7), set(), 0
    n_s = len(robot.spheres)
    for k in range(int(round(seconds / DT))):
        q, dq = np.asarray(state.q), np.asarray(state.dq)
        tau = policy(Observation(k * DT, q, dq, as_matrix(model.mass(state), 7, 7),
                                 np.asarray(model.coriolis(state)), None))
        last = limit_rate(tau, last)
        control.writeOnce(Torques(last))
        state, _ = control.readOnce()
        h = robot.clearance().reshape(-1, n_s).min(axis=1)
        hit |= set(np.flatnonzero(h < 0.0).tolist())
        cost += robot.cost()
    return hit, cost


@pytest.mark.slow
@pytest.mark.parametrize("model", ["oracle", "own"])
def test_a_table_and_a_box_in_the_trackers_way_stay_clear(model):
    """The tracker, blind to obstacles, starting 1 cm above a table at the mount with a box
    on the table in its way: unfiltered it takes the hand into the box and (with the 1 kg
    payload its model does not know, sagging) into the table; through the bridge no step
    has cost (a sphere inside either, an arm geom touching either: the stand-in's true
    state), with the exact model (``"oracle"``: no payload, no joint damping, so the robot's
    model is the plant; the hand stops short of the box) and with the robot's own model and
    the default torque-error bound (``"own"``: the bound's worst-case residual lifts the hand
    off the table, and it passes above the box). Stepped on the fake clock: no step falls
    back, the run is deterministic."""
    oracle = model == "oracle"
    plant = {"payload_mass": 0.0, "damping": 0.0} if oracle else {}
    hit, cost = _hits_without_the_filter(
        SimulatedFranka([TABLE, BOX], q0=LOW_Q0, realtime=False, **plant), 4.0)
    assert cost > 0 and hit == ({1} if oracle else {0, 1})
    robot = SimulatedFranka([TABLE, BOX], q0=LOW_Q0, realtime=False, **plant)
    assert [o.kind for o in robot.obstacles] == ["plane", "box"]
    assert robot.clearance().min() > 0.0 and not robot.cost()
    bridge, _, _ = _bridge(robot, agent="nominal",
                           torque_error=0.0 if oracle else (3, 3, 3, 3, 1, 1, 1))
    closest = []  # the true clearance of each obstacle after every tick
    true_cost = bridge.cost
    bridge.cost = lambda: closest.append(robot.clearance().reshape(2, -1).min(1)) or true_cost()
    report = bridge.run(4.0)
    assert report.stop_reason == "completed" and report.steps == 4000
    assert report.cost_steps == 0 and report.filter_active_steps > 1000
    table, box = np.min(closest, axis=0)
    assert table > 0.0 and box > 0.0
    if oracle:
        assert box < 0.03  # the hand went as far as the box let it


def test_the_stand_ins_obstacles_are_mujoco_geoms_of_their_type_that_follow_them():
    moving = {**BOX, "start": [0.8, -0.2, 0.05], "start_time": 0.0, "speed": 0.3}
    robot = SimulatedFranka([TABLE, moving, {"type": "capsule", "position": [0.5, 0.3, 0.3],
                                             "radius": 0.03, "half_length": 0.1}],
                            realtime=False)
    m = robot.model
    kinds = [int(m.geom(f"obstacle{i}").type[0]) for i in range(3)]
    assert kinds == [mujoco.mjtGeom.mjGEOM_PLANE, mujoco.mjtGeom.mjGEOM_BOX,
                     mujoco.mjtGeom.mjGEOM_CAPSULE]
    control = robot.start_torque_control()
    for _ in range(500):
        control.readOnce()
        control.writeOnce(Torques(np.zeros(7)))
    box = robot.data.geom_xpos[m.geom("obstacle1").id]
    np.testing.assert_allclose(box, robot.obstacles[1].state(robot.time)[0], atol=1e-15)
    assert box[0] < 0.8  # on its way
    np.testing.assert_allclose(robot.data.geom_xmat[m.geom("obstacle1").id].reshape(3, 3),
                               robot.obstacles[1].shape.rotation, atol=1e-9)
    assert not robot.contact()
    # the contact check sees the arm's meshes: a box about the end-effector, a table through
    # the hand (its plane by the geoms' bounding spheres)
    tip = robot.reference_center
    for obstacle in ({"type": "box", "position": tip.tolist(), "half_sizes": [0.02] * 3},
                     {**TABLE, "position": [0.0, 0.0, tip[2]]}):
        touching = SimulatedFranka([obstacle], realtime=False)
        assert touching.contact() and touching.cost()


def test_the_stand_ins_cost_counts_the_arm_touching_itself():
    """The stand-in's cost is the simulation's: a folded arm (the hand on link 1, no obstacle
    near) is a self-contact and a cost, the ready pose neither, and the flag is the
    simulation env's at the same joint angles."""
    from afvsgp_gym.envs.franka import FrankaObstacleEnv

    robot = SimulatedFranka(realtime=False)
    env = FrankaObstacleEnv()
    folded = np.array([0.0, 0.0, 0.0, -2.8, 0.0, -0.3, 0.785])  # test_self_collision's
    for q, touching in ((env.q_home, False), (folded, True)):
        robot.set_state(q, np.zeros(7))
        env.set_state(q, np.zeros(7))
        _, _, _, _, info = env.step(np.zeros(7))
        robot.set_state(env.data.qpos[:7], env.data.qvel[:7])
        assert robot.self_contact() == info["self_contact"] == touching
        assert robot.cost() == touching and robot.clearance().min() > 0.0
    env.close()


def test_self_collision_barriers_are_on_by_default_with_the_arm_spheres():
    """On by default, as in the simulation: the simulation's 93 pairs after the obstacle
    pairs, and the loop runs (stepped) without cost; ``self_collision=False`` leaves them
    out; other spheres than the Panda's arm spheres have none by default, and asking for them
    is refused by name."""
    from afvsgp_gym.robots.run import run_simulated

    assert _bridge(self_collision=False)[0].barriers.n_pair_rows == 21
    report = run_simulated(0.5, realtime=False, budget=1.0)
    assert report.stop_reason == "completed" and report.cost_steps == 0
    assert report.self_collision_barriers == 93 and report.barriers == 21 + 93 + 28
    robot = SimulatedFranka(realtime=False)
    kwargs = dict(chain=robot.kinematics, obstacle_radii=[0.05],
                  obstacles=robot.obstacle_estimate, limits=robot.joint_limits,
                  spheres=robot.spheres[14:])
    assert build_bridge(robot, robot.load_model(), Torques, **kwargs).barriers.n_pair_rows == 7
    with pytest.raises(ValueError, match="self_collision=True needs"):
        build_bridge(robot, robot.load_model(), Torques, self_collision=True, **kwargs)


@pytest.mark.parametrize("self_collision, safe", [(None, True), (False, False)],
                         ids=["default", "without"])
def test_the_self_collision_barriers_stop_a_swinging_joint_folding_the_arm(self_collision,
                                                                          safe):
    """``swing4`` (seed 1: full torque on joint 4, the others damped) folds the forearm onto
    the upper arm 0.63 s in without the self-collision barriers (the test can fail); with
    them, the default, no tick has cost."""
    from afvsgp_gym.robots.run import run_simulated

    report = run_simulated(1.2, agent="swing4", seed=1, realtime=False, budget=1.0,
                           torque_error=[3, 3, 3, 3, 1, 1, 1], self_collision=self_collision)
    assert report.stop_reason == "completed" and report.steps == 1200
    assert (report.cost_steps == 0) == safe


def test_the_policies_built_to_break_the_filter():
    """``ram`` pulls the end-effector point at the nearest obstacle (its torque moves the
    point toward it: ``(J tau) . (p_o - p) > 0``); ``swingN`` puts full torque on joint N, its
    sign from the seed and switching every second, the others damped; ``random`` is uniform
    within the limits and seeded. Every output is within the torque limits."""
    from afvsgp_gym.robots.libfranka import TAU_MAX
    from afvsgp_gym.robots.terms import ObstacleEstimate

    robot = SimulatedFranka(realtime=False)
    q0 = np.asarray(robot.read_once().q, dtype=np.float64)
    kin = SphereKinematics(robot.kinematics, [7], [(0.0, 0.0, 0.21)])
    p = kin.positions(q0)[0]
    target = p + [0.1, -0.2, 0.05]
    est = ObstacleEstimate(np.array([target, p + [2.0, 0, 0]]), np.zeros((2, 3)),
                           np.zeros((2, 3)))
    dq = np.full(7, 0.3)
    obs = Observation(0.0, q0, dq, np.eye(7), np.zeros(7), est)
    jac = kin(q0, np.zeros(7))[2][0]
    tau = make_robot_policy("ram", robot.kinematics, q0)(obs)
    assert (jac @ tau) @ (target - p) > 0 and np.all(np.abs(tau) <= TAU_MAX)
    for seed, sign in ((0, 1.0), (1, -1.0)):
        swing = make_robot_policy("swing4", robot.kinematics, q0, seed)
        first, later = swing(obs), swing(obs._replace(t=1.5))
        assert first[3] == sign * TAU_MAX[3] and later[3] == -first[3]
        np.testing.assert_array_equal(np.delete(first, 3), -np.delete(dq * TAU_MAX, 3))
    for bad in (-1, 1.5, None, "0"):
        with pytest.raises(ValueError, match="seed must be an integer"):
            make_robot_policy("swing2", robot.kinematics, q0, bad)
    with pytest.raises(ValueError, match="agent"):
        make_robot_policy("greedy", robot.kinematics, q0)
    a, b = (make_robot_policy("random", robot.kinematics, q0, 7) for _ in range(2))
    draws = np.array([a(obs) for _ in range(200)])
    np.testing.assert_array_equal(draws[0], b(obs))
    assert np.all(np.abs(draws) <= TAU_MAX) and np.all(draws.max(0) > 0.8 * TAU_MAX)
