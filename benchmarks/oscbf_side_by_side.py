"""Our filter beside OSCBF's on OSCBF's cluttered-tabletop scene, timed in one run.

    OPENBLAS_NUM_THREADS=1 taskset -c 0 python benchmarks/oscbf_side_by_side.py --oscbf PATH
        [--steps N] [--quick]

``PATH`` is a copy of StanfordASL/oscbf (it is not on the package registry, and it is not a
dependency of this package or its CI). It runs with the jax it pins, which takes numpy 1.26;
this package runs with it too:

    pip install "jax[cpu]==0.4.30" jaxlib==0.4.30 cbfpy==0.0.1 qpax six networkx lxml trimesh
    pip install -e PATH --no-deps
    pip install -e . -c <(echo numpy==1.26.4)

**The scene** is OSCBF's cluttered-tabletop demo (``oscbf/examples/cluttered_tabletop.py``):
25 spheres drawn as it draws them (numpy's legacy generator seeded 0; centres uniform in
[0.2, 0.8] x [-0.4, 0.4] x [0.1, 0.3] m, radii uniform in [0.01, 0.1] m, the first 25 of 50)
and a table at z = 0.1 m, each against the arm's 21 spheres: 21 x 26 = 546 constraints. The
Panda's base is at the origin in both. Ours adds the 28 joint-limit barriers.

**Ours:** the nominal tracker behind ``SafetyFilter`` on the static Franka scenario with the
scene's obstacles in place of its own (``obstacles=``, a ``"plane"`` for the table), in three
configurations (:class:`afvsgp_gym.benchmarks.arm.TimedEpisode`, whose module docstring says
what ``step``, the filter and the learning, and ``env.step`` time): the model known (``"oracle"``,
no learning), and learning with nothing of the dynamics known (``nominal_model="kinematic"``)
by the shared learner (``"afvsgp-shared"``) and by the paper's per-pair learners
(``"afvsgp"``, ``SafetyFilter``'s default: 546 + 7 learners).

**OSCBF's step** is its whole torque controller as its demo and speed test run it, compiled
with ``jax.jit``: the operational-space nominal torque (``PoseTaskTorqueController``, the
demo's gains) and cbfpy's QP over the demo's barriers (its ``CollisionsConfig``:
``alpha(h) = alpha_2(h) = 10 h``), with the model known (OSCBF does not learn). Each episode of
ours advances in lockstep with OSCBF's calls, one call at the state the episode is in after
each of its timed steps, toward the same reference (so that each ratio is measured on the
same seconds, and neither shares the caches with a third configuration); after them OSCBF
runs at random states as its own speed test draws them (joint angles N(home, 0.1) about its
test's home, velocities N(0, 0.1), targets uniform in its test's box).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np

from afvsgp_gym.benchmarks._machine import calibration_line, machine
from afvsgp_gym.benchmarks.arm import TimedEpisode

#: the demo's table height (m) and the bounds it draws its spheres in
TABLE_Z = 0.1
BOX_LOW, BOX_HIGH = (0.2, -0.4, 0.1), (0.8, 0.4, 0.3)
RADIUS_LOW, RADIUS_HIGH = 0.01, 0.1
#: the box OSCBF's speed test draws its end-effector targets in (m)
TARGET_LOW, TARGET_HIGH = np.array([0.15, -0.25, 0.25]), np.array([0.75, 0.25, 0.75])


def oscbf_clutter(n: int = 25, draws: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """The demo's sphere centres (n, 3) and radii (n,): it seeds numpy's legacy generator
    with 0 and draws ``draws`` centres, then ``draws`` radii, and keeps the first ``n``."""
    rng = np.random.RandomState(0)
    centres = rng.uniform(low=BOX_LOW, high=BOX_HIGH, size=(draws, 3))
    radii = rng.uniform(low=RADIUS_LOW, high=RADIUS_HIGH, size=(draws,))
    return centres[:n], radii[:n]


def our_obstacles(centres: np.ndarray, radii: np.ndarray) -> list[dict[str, Any]]:
    """The scene as ``FrankaObstacleEnv(obstacles=)``: the spheres, then the table."""
    return [{"position": [float(v) for v in c], "radius": float(r)}
            for c, r in zip(centres, radii, strict=True)] + [
        {"type": "plane", "position": [0.0, 0.0, TABLE_Z], "normal": [0.0, 0.0, 1.0]}]


def configs(obstacles: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Our three configurations (TimedEpisode specs) on the scene."""
    return {
        "ours, model known (oracle)": {"learner": "oracle", "obstacles": obstacles},
        "ours, shared learner": {"learner": "afvsgp-shared", "nominal_model": "kinematic",
                                 "obstacles": obstacles},
        "ours, per-pair learners": {"learner": "afvsgp", "nominal_model": "kinematic",
                                    "obstacles": obstacles},
    }


class OSCBFController:
    """OSCBF's compiled torque controller on the scene (see the module docstring):
    ``controller(z, des)`` returns the filtered torque for the state ``z = [q, q']`` and the
    desired end-effector state ``des = [p, R (9), v, w]``."""

    def __init__(self, path: str, centres: np.ndarray, radii: np.ndarray):
        sys.path.insert(0, path)
        import jax
        import jax.numpy as jnp
        import oscbf  # noqa: F401  (turns on jax's 64-bit floats, as OSCBF runs)
        from cbfpy import CBF
        from oscbf.core.controllers import PoseTaskTorqueController
        from oscbf.core.manipulator import load_panda
        from oscbf.core.oscbf_configs import OSCBFTorqueConfig

        robot = load_panda()
        n = robot.num_joints

        @jax.tree_util.register_static
        class Collisions(OSCBFTorqueConfig):
            """The demo's barriers: every (robot sphere, obstacle) pair and the table."""

            def __init__(self) -> None:
                self.centres, self.radii = np.atleast_2d(centres), np.ravel(radii)
                super().__init__(robot)

            def h_2(self, z, **kwargs):
                spheres = self.robot.link_collision_data(z[:n])
                pos, rad = spheres[:, :3], spheres[:, 3]
                gaps = jnp.linalg.norm(pos[:, None, :] - self.centres[None], axis=2)
                pairs = (gaps - rad[:, None] - self.radii[None]).reshape(-1)
                return jnp.concatenate([pairs, pos[:, 2] - TABLE_Z - rad])

            def alpha(self, h):
                return 10.0 * h

            def alpha_2(self, h_2):
                return 10.0 * h_2

        cbf = CBF.from_config(Collisions())
        osc = PoseTaskTorqueController(
            n_joints=n, kp_task=np.array([50.0] * 3 + [20.0] * 3),
            kd_task=np.array([20.0] * 3 + [10.0] * 3), kp_joint=10.0, kd_joint=5.0,
            tau_min=None, tau_max=None)
        posture = jnp.array([0.0, -np.pi / 6, 0.0, -3 * np.pi / 4, 0.0, 5 * np.pi / 9, 0.0])

        @jax.jit
        def control(z, des):
            q, qd = z[:n], z[n:]
            M, M_inv, g, c, J, ee = robot.torque_control_matrices(q, qd)
            u = osc(q, qd, pos=ee[:3, 3], rot=ee[:3, :3], des_pos=des[:3],
                    des_rot=des[3:12].reshape(3, 3), des_vel=des[12:15],
                    des_omega=des[15:18], des_accel=jnp.zeros(3), des_alpha=jnp.zeros(3),
                    des_q=posture, des_qdot=jnp.zeros(n), J=J, M=M, M_inv=M_inv, g=g, c=c)
            return cbf.safety_filter(z, u)

        self.control = control
        #: every (robot sphere, obstacle) pair and every robot sphere against the table
        self.n_constraints = (len(radii) + 1) * robot.link_collision_data(np.zeros(n)).shape[0]
        #: its speed test's home; the targets' orientation is the end effector's there
        self.home = np.array([0.0, -np.pi / 3, 0.0, -5 * np.pi / 6, 0.0, np.pi / 2, 0.0])
        self.rot = np.asarray(robot.ee_rotation(self.home)).ravel()
        t0 = time.perf_counter()
        self(np.concatenate([self.home, np.zeros(n)]),
             self.target(0.5 * (TARGET_LOW + TARGET_HIGH), np.zeros(3)))
        self.compile_s = time.perf_counter() - t0

    def target(self, p: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The desired end-effector state at ``p`` moving at ``v``, turned as at home."""
        return np.concatenate([p, self.rot, v, np.zeros(3)]).astype(np.float64)

    def __call__(self, z: np.ndarray, des: np.ndarray) -> np.ndarray:
        return np.asarray(self.control(z, des).block_until_ready())


class OSCBFStep:
    """Timed calls of ``controller``: at the state and reference of the episode ``source``
    (a :class:`TimedEpisode`) each time it has taken a timed step, or, without a source,
    ``steps`` calls at random states as OSCBF's speed test draws them."""

    def __init__(self, controller: OSCBFController, source: TimedEpisode | None = None,
                 steps: int = 1000, seed: int = 0):
        self.controller, self.source = controller, source
        self.rng = np.random.RandomState(seed)
        self.remaining = steps if source is None else 0
        self.out: list[float] = []

    def _inputs(self) -> tuple[np.ndarray, np.ndarray]:
        if self.source is None:
            q = self.rng.multivariate_normal(self.controller.home, 0.1 * np.eye(7))
            qd = self.rng.multivariate_normal(np.zeros(7), 0.1 * np.eye(7))
            p = TARGET_LOW + self.rng.rand(3) * (TARGET_HIGH - TARGET_LOW)
            v = -1.0 + 2.0 * self.rng.rand(3)
        else:
            obs = self.source.obs
            k = self.source.policy._impl.k  # the reference's place in the observation
            q, qd, p, v = obs[:7], obs[7:14], obs[k:k + 3], obs[k + 3:k + 6]
        return (np.concatenate([q, qd]).astype(np.float64),
                self.controller.target(np.asarray(p, float), np.asarray(v, float)))

    def step(self) -> None:
        """One timed call, if the source has just taken a timed step (or there is none)."""
        if self.source is None:
            if self.remaining <= 0:
                return
            self.remaining -= 1
        elif len(self.source.out["step"]) <= len(self.out):
            return
        z, des = self._inputs()
        t0 = time.perf_counter()
        self.controller(z, des)
        self.out.append(time.perf_counter() - t0)


def _count_cost(ep: TimedEpisode, counter: dict[str, int]) -> None:
    """Count ``ep``'s steps with cost in ``counter`` (a thin wrapper of its env's step)."""
    step = ep.env.step

    def counted(action):
        out = step(action)
        counter["cost"] += int(out[4].get("cost", 0.0) > 0)
        counter["steps"] += 1
        return out

    ep.env.step = counted


def run(path: str, steps: int = 1000, seed: int = 0) -> dict[str, float]:
    """Median and p99 (s) per control step of each of our configurations and of OSCBF's
    controller at the same states, each pair in its own lockstep (one episode of ours
    beside OSCBF's calls, so that neither shares the caches with a third), then OSCBF at
    random states; and the ratios of ours to OSCBF's in each pair."""
    centres, radii = oscbf_clutter()
    controller = OSCBFController(path, centres, radii)
    out: dict[str, float] = {"OSCBF: constraints": float(controller.n_constraints),
                             "OSCBF: first call (compilation)_s": controller.compile_s}
    for name, spec in configs(our_obstacles(centres, radii)).items():
        ep = TimedEpisode(spec, steps=steps, seed=seed)
        cost = {"cost": 0, "steps": 0}
        _count_cost(ep, cost)
        osc = OSCBFStep(controller, source=ep)
        order: list[Any] = [ep, osc]
        while ep.remaining > 0:
            for x in order:
                x.step()
            order.reverse()
        res = ep.result()
        for part, key in (("step", "filter + learning"), ("env_step", "env.step")):
            out[f"{name}: {key} median_s"] = float(np.median(res[part]))
            out[f"{name}: {key} p99_s"] = float(np.percentile(res[part], 99))
        out[f"{name}: barriers"] = float(res["n_barriers"][0])
        out[f"{name}: barriers in program (mean)"] = float(np.mean(res["n_active"]))
        out[f"{name}: steps with cost"] = float(cost["cost"])
        t = np.asarray(osc.out)
        out[f"{name}: OSCBF at its states median_s"] = float(np.median(t))
        out[f"{name}: OSCBF at its states p99_s"] = float(np.percentile(t, 99))
        out[f"{name}: filter + learning median / OSCBF's"] = (
            out[f"{name}: filter + learning median_s"] / float(np.median(t)))
    rand = OSCBFStep(controller, steps=steps, seed=seed)
    while rand.remaining > 0:
        rand.step()
    t = np.asarray(rand.out)
    out["OSCBF at its test's random states: median_s"] = float(np.median(t))
    out["OSCBF at its test's random states: p99_s"] = float(np.percentile(t, 99))
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--oscbf", required=True, help="path of a copy of StanfordASL/oscbf")
    p.add_argument("--steps", type=int, default=1000, help="timed control steps (1000)")
    p.add_argument("--quick", action="store_true", help="200 timed steps")
    args = p.parse_args(argv)
    if args.steps <= 0:
        p.error(f"--steps must be positive, got {args.steps}")
    print(machine())
    print(calibration_line(), flush=True)
    import jax

    print(f"jax {jax.__version__}, numpy {np.__version__}", flush=True)
    for key, val in run(args.oscbf, 200 if args.quick else args.steps).items():
        shown = f"{val * 1e6:10.1f} us" if key.endswith("_s") else f"{val:10.3f}"
        print(f"{key:72s} {shown}")


if __name__ == "__main__":
    main()
