"""Safety-filter benchmark: acceptance sweeps (violations, min h, tracking) and timing.

``run(quick)`` returns ``{name: float}``; ``main()`` prints the tables. Command line::

    python -m afvsgp_gym.benchmarks.filter [--quick] [--no-sweeps]

Timing is per call on the current process (pin it to one core, e.g. ``taskset -c 0``, with
``OMP_NUM_THREADS=1``). Episodes are counted by :mod:`afvsgp_gym.evaluation` (the CLI's
runner): tracking error "away from the obstacle" is ``|p - r|`` (m) at the steps where the
reference's sphere keeps at least 5 cm from every obstacle (``info["reference_h"] >= 0.05``),
i.e. where an ideal tracker has no reason to deviate; it is reported next to the same figure
for the unfiltered nominal controller on the same seed.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import numpy as np

SCENARIOS = {
    "pointmass": ("afvsgp_gym/PointMassObstacle-v0", {}),
    "franka_static": ("afvsgp_gym/FrankaObstacleStatic-v0", {}),
    "franka_dynamic": ("afvsgp_gym/FrankaObstacleDynamic-v0", {}),
    "franka_random": ("afvsgp_gym/FrankaObstacleRandom-v0", {}),
}


def run_episode(
    scenario: str,
    learner: str | None,
    seed: int,
    env_kwargs: dict | None = None,
    probe: Callable[[Any], dict] | None = None,
    **filter_options: Any,
) -> dict[str, float]:
    """One seeded episode with the nominal tracker; ``learner=None`` runs it unfiltered.

    Built and counted as :func:`afvsgp_gym.evaluation.run_spec` does (the CLI's episode
    runner). Returns violations (steps with h < 0), cost steps, contact steps, min h,
    fallbacks (backup or max-margin steps), interventions, mean/max tracking error away from
    the obstacle, filter time median/p99 (s) and wall time (s). ``probe(controller)`` (with a
    learner) is called once, right after the warm-up fit; its dict is merged into the result.
    """
    from afvsgp_gym.evaluation import EpisodeSpec, make_env, make_policy
    from afvsgp_gym.evaluation import run_episode as run_counted

    env_id, kw = SCENARIOS[scenario]
    spec = EpisodeSpec(env_id, seed, learner=learner, env_kwargs={**kw, **(env_kwargs or {})},
                       filter_kwargs=filter_options)
    probed: dict = {}

    def on_step(info: dict) -> None:
        if probe is not None and learner is not None and not probed \
                and not env.controller.warming_up:
            probed.update(probe(env.controller) or {"probed": True})

    t0 = time.perf_counter()
    env = make_env(spec)
    try:
        rec, _ = run_counted(env, make_policy(spec.agent, env, seed=seed), seed, on_step=on_step)
    finally:
        env.close()
    wall = time.perf_counter() - t0

    def num(key: str) -> float:
        return np.nan if rec[key] is None else float(rec[key])

    return {
        "violations": num("violation_steps"),
        "cost_steps": num("cost_steps"),
        "contacts": num("contact_steps"),
        "min_h": num("min_h"),
        "fallbacks": num("infeasible_steps"),
        "interventions": num("interventions"),
        "track_mean": num("tracking_error_mean"),
        "track_max": num("tracking_error_max"),
        "filter_median_s": num("filter_time_median_s"),
        "filter_p99_s": num("filter_time_p99_s"),
        "steps": num("steps"),
        "wall_s": wall,
        **probed,
    }


def sweep(scenario: str, learners, seeds, **filter_options) -> dict[str, dict[str, float]]:
    """Aggregate :func:`run_episode` over seeds for each learner (and the unfiltered run)."""
    out = {}
    for learner in learners:
        rows = [run_episode(scenario, learner, s, **filter_options) for s in seeds]
        out[str(learner)] = {
            "episodes": float(len(rows)),
            "episodes_violating": float(sum(r["violations"] > 0 for r in rows)),
            "episodes_with_cost": float(sum(r["cost_steps"] > 0 for r in rows)),
            "violation_steps": float(sum(r["violations"] for r in rows)),
            "contact_steps": float(sum(r["contacts"] for r in rows)),
            "min_h": float(min(r["min_h"] for r in rows)),
            "fallbacks": float(sum(r["fallbacks"] for r in rows)),
            "track_mean": float(np.nanmean([r["track_mean"] for r in rows])),
            "track_max": float(np.nanmax([r["track_max"] for r in rows])),
            "wall_s": float(sum(r["wall_s"] for r in rows)),
        }
    return out


# ---------------------------------------------------------------------- timing
def time_socp(n: int = 2000, m: int = 7, n_barriers: int = 1, seed: int = 0) -> np.ndarray:
    """Per-solve times (s) of the chance-constrained SOCP alone on random active instances."""
    from afvsgp_gym.cbf import SOCPFilter

    rng = np.random.default_rng(seed)
    f = SOCPFilter(-np.ones(m), np.ones(m))
    out = np.empty(n)
    for i in range(n):
        a = rng.normal(size=(n_barriers, m))
        G = 0.2 * rng.normal(size=(n_barriers, m + 1, m + 1))
        u_nom = rng.uniform(-1, 1, m)
        a0 = -(a @ u_nom) - 0.3  # the nominal action violates: the cone program runs
        t0 = time.perf_counter()
        f.solve(u_nom, a0, a, G)
        out[i] = time.perf_counter() - t0
    return out


def time_filtered_step(
    scenario: str = "franka_static", learner: str = "afvsgp", steps: int = 1500, seed: int = 0
) -> dict[str, np.ndarray]:
    """Per-step times (s) after warm-up: ``filter`` (predict_affine + SOCP), ``observe``
    (eq. 48 + learner update) and their sum, the full filtered step without the simulator;
    ``filter_active`` / ``filter_inactive``: the filter times of the steps where a cone
    program was solved / where the proposal was already safe (early exit)."""
    import gymnasium as gym

    import afvsgp_gym  # noqa: F401
    from afvsgp_gym.agents import NominalController
    from afvsgp_gym.cbf import SafetyController
    from afvsgp_gym.wrappers.safety_filter import with_env_suggestions

    env_id, kw = SCENARIOS[scenario]
    env = gym.make(env_id, **kw)
    base = env.unwrapped
    ctrl = SafetyController(
        env.action_space.low,
        env.action_space.high,
        base.n_barriers,
        learner=learner,
        **with_env_suggestions(base, learner, {
            "seed": seed, "relative_degree": base.relative_degree,
            "warmup_samples": min(200, base.warmup_steps - 1)}),
    )
    ctrl.prepare_programs()  # as a real-time loop would: no solver built while timed
    policy = NominalController(env)
    obs, _ = env.reset(seed=seed)
    t_f, t_o, act = [], [], []
    for _ in range(base.warmup_steps + steps):
        terms = base.barrier_terms("nominal")
        true = base.barrier_terms("true") if learner == "oracle" else None
        u_nom = policy(obs)
        t0 = time.perf_counter()
        res = ctrl.filter(u_nom, terms, true)
        t1 = time.perf_counter()
        obs, _, term, trunc, _ = env.step(res.u.astype(np.float32))
        after = base.barrier_terms("nominal")
        t2 = time.perf_counter()
        ctrl.observe(terms, res.u, after, base.dt)
        t3 = time.perf_counter()
        if not ctrl.warming_up:
            t_f.append(t1 - t0)
            t_o.append(t3 - t2)
            act.append(res.active)
        if term or trunc:
            obs, _ = env.reset()
    env.close()
    t_f, t_o, act = np.array(t_f), np.array(t_o), np.array(act, dtype=bool)
    out = {"filter": t_f, "observe": t_o, "step": t_f + t_o}
    if act.any():
        out["filter_active"] = t_f[act]
    if not act.all():
        out["filter_inactive"] = t_f[~act]
    return out


def run(quick: bool = False, sweeps: bool | None = None) -> dict[str, float]:
    """Timing figures (s) and, unless ``quick`` (or ``sweeps=False``), the acceptance sweeps
    (counts, m): point mass 20 seeds, Franka static and dynamic 10 seeds each, for the
    unfiltered tracker ("None"), "none", "oracle" and "afvsgp"."""
    sweeps = (not quick) if sweeps is None else sweeps
    out: dict[str, float] = {}
    t = time_socp(300 if quick else 3000)
    out["socp_median_s"], out["socp_p99_s"] = float(np.median(t)), float(np.percentile(t, 99))
    for learner in ("oracle", "afvsgp"):
        ts = time_filtered_step("franka_static", learner, steps=300 if quick else 2000)
        for part, arr in ts.items():
            out[f"franka_{learner}_{part}_median_s"] = float(np.median(arr))
            out[f"franka_{learner}_{part}_p99_s"] = float(np.percentile(arr, 99))
        if "filter_active" in ts:
            out[f"franka_{learner}_active_fraction"] = len(ts["filter_active"]) / len(ts["filter"])
    if sweeps:
        plan = [
            ("pointmass", (None, "none", "oracle", "afvsgp"), range(20)),
            ("franka_static", (None, "none", "oracle", "afvsgp"), range(10)),
            ("franka_dynamic", (None, "none", "oracle", "afvsgp"), range(10)),
        ]
        for scenario, learners, seeds in plan:
            for learner, row in sweep(scenario, learners, seeds).items():
                for key, val in row.items():
                    out[f"{scenario}_{learner}_{key}"] = val
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short timing, no sweeps")
    parser.add_argument("--no-sweeps", action="store_true", help="full timing only")
    args = parser.parse_args(argv)
    res = run(quick=args.quick, sweeps=False if args.no_sweeps else None)
    width = max(len(k) for k in res)
    for key, val in res.items():
        unit = (
            f"{val * 1e6:12.1f} us" if key.endswith("_s") and "wall" not in key else f"{val:12.4g}"
        )
        print(f"{key:<{width}}  {unit}")


if __name__ == "__main__":
    main()
