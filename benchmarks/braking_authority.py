"""Can the Franka's torque limits stop every barrier the filter lets approach? (docs/safety.md)

The HOCBF of a relative-degree-2 barrier asks, where ``psi_1 = h' + alpha_1(h) = 0`` (the
fastest approach it allows, ``v = -h' = alpha_1(h)``), for ``h'' >= alpha_1 alpha_1'``:

- the linear chain ``alpha_1 = a h``: ``h'' >= a v``, growing without bound with the speed;
- the braking curve of :func:`afvsgp_gym.cbf.hocbf.braking_alpha` with deceleration ``A``:
  ``h'' >= A v / (v + A / a)``, never more than ``A``.

The program of that barrier alone is feasible there when the torque box can make ``h''`` that
large. This script samples states of the arm (joint angles in range, speeds within the
datasheet limits, the plant with payloads of 0 to 3 kg), every safety sphere, and directions
``n`` towards an obstacle that the sphere approaches (head-on and random), and computes the
best ``h''`` along ``n`` over the torque box, ``n.(J q''_0 + J' q') + sum_j |(n' J M^-1)_j|
tau_max_j`` (the curvature term, >= 0, left out: conservative). It reports the share of samples
where each route's demand exceeds it, and for the joint range barriers (``h'' = -+q''_j``,
linear demand ``a v``, braking demand ``A_j v / (v + A_j / a)``) likewise.

    python benchmarks/braking_authority.py [--states 3000] [--json out.json]

What it does not cover: several barriers active at once (their joint feasibility), the
learned filter's uncertainty, and the discrete control period; the adversarial sweep
(benchmarks/configs/adversarial.toml) measures the closed loop.
"""

from __future__ import annotations

import argparse
import json
import time

import mujoco
import numpy as np

from afvsgp_gym.envs.franka import FrankaObstacleEnv
from afvsgp_gym.evaluation import cpu_model


def _demand(v: np.ndarray, gain: float, decel: float) -> np.ndarray:
    """``alpha_1 alpha_1'`` where ``alpha_1(h) = v`` (the boundary ``psi_1 = 0``)."""
    if not np.isfinite(decel):
        return gain * v
    return decel * v / (v + decel / gain)


def sample(states: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    routes = {"linear a=4": (4.0, np.inf), "linear a=1.3": (1.3, np.inf),
              "braking A=5, a=4": (4.0, FrankaObstacleEnv.OBSTACLE_DECELERATION)}
    sphere_fail = {name: 0 for name in routes}
    joint_fail = {"linear a=4": np.zeros(7, int), "braking (datasheet A_j), a=4": np.zeros(7, int)}
    n_sphere = n_joint = 0
    ratios: dict[str, list] = {name: [] for name in routes}  # authority / demand per sample
    fast: dict[str, list] = {name: [] for name in routes}  # the same, approach > 1.5 m/s
    for payload in (0.0, 1.0, 3.0):
        env = FrankaObstacleEnv("static", payload_mass=payload, nominal_model="exact")
        env.reset(seed=0)
        m, d = env.model, env.data
        lim = env.joint_limits
        tmax = env.action_scale
        for _ in range(states // 3):
            q = rng.uniform(lim.lower + lim.range_margin, lim.upper - lim.range_margin)
            qd = rng.uniform(-1.0, 1.0, 7) * (lim.max_speed - lim.speed_margin)
            env.set_state(q, qd)
            _, v_s, jac, jdq = env._spheres
            minv = np.empty((7, 7))
            mujoco.mj_solveM(m, d, minv, np.eye(7))
            qdd0 = d.qacc[:7].copy()
            for s in range(len(v_s)):
                speed = np.linalg.norm(v_s[s])
                if speed < 1e-3:
                    continue
                for n in (-v_s[s] / speed, rng.normal(size=3)):
                    n = n / np.linalg.norm(n)
                    v = -n @ v_s[s]
                    if v <= 1e-3:
                        continue
                    g = n @ jac[s] @ minv * tmax
                    best = n @ (jac[s] @ qdd0 + jdq[s]) + np.abs(g).sum()
                    n_sphere += 1
                    for name, (a, A) in routes.items():
                        ratio = float(best / _demand(np.array(v), a, A))
                        sphere_fail[name] += ratio < 1.0
                        ratios[name].append(ratio)
                        if v > 1.5:
                            fast[name].append(ratio)
            # joint ranges: the best deceleration of joint j towards each stop
            auth = np.abs(minv) * tmax
            for j in range(7):
                v = abs(qd[j])
                best = auth[j].sum() - np.sign(qd[j]) * qdd0[j]
                n_joint += j == 0
                joint_fail["linear a=4"][j] += best < 4.0 * v
                joint_fail["braking (datasheet A_j), a=4"][j] += best < _demand(
                    np.array(v), 4.0, FrankaObstacleEnv.RANGE_DECELERATION[j])
    return {
        "sphere_samples": n_sphere,
        "sphere_infeasible_share": {k: v / n_sphere for k, v in sphere_fail.items()},
        "authority_over_demand_percentiles": {
            k: dict(zip(("min", "0.01%", "1%", "median"),
                        np.percentile(r, [0, 0.01, 1, 50]).round(3).tolist(), strict=True))
            for k, r in ratios.items()},
        "fast_approach_samples": len(next(iter(fast.values()))),
        "fast_authority_over_demand_percentiles": {
            k: dict(zip(("min", "1%", "median"), np.percentile(r, [0, 1, 50]).round(3).tolist(),
                        strict=True)) for k, r in fast.items()},
        "joint_samples": n_joint,
        "joint_infeasible_share": {k: (v / n_joint).tolist() for k, v in joint_fail.items()},
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--states", type=int, default=3000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", default=None)
    args = p.parse_args()
    t0 = time.perf_counter()
    res = sample(args.states, args.seed)
    res.update(states=args.states, seed=args.seed, seconds=time.perf_counter() - t0,
               machine=cpu_model(), date=time.strftime("%Y-%m-%d"))
    print(json.dumps(res, indent=1))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
