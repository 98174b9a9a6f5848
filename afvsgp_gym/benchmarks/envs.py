"""Environment speed on one core: env steps per second, barrier terms included.

Each figure is ``steps / wall time`` of a loop that calls ``env.step(a)`` and then
``env.unwrapped.barrier_terms("nominal")`` and ``barrier_terms("true")`` (what the safety
filter and its evaluation read every step; ``step`` itself computes both to report
``info["delta_b_true"]``). Actions are pre-drawn uniform samples; episodes are reset when they
end (reset time included). Gymnasium's ``Ant-v5`` (plain ``env.step``) is measured in the same
run as a reference point when it can be made. "closed loop" adds the NominalController.
Rates are given per wall-clock second and per CPU second of this process (the latter is the
meaningful one on a shared machine; everything runs in one thread).

Cases run in interleaved rounds (every case once per round); figures are medians over the
rounds, ratios to Ant-v5 the median of the per-round ratios.

Run: ``python -m afvsgp_gym.benchmarks.envs [--quick]``.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import gymnasium as gym
import numpy as np

import afvsgp_gym  # noqa: F401  (registers the ids)
from afvsgp_gym.benchmarks._machine import machine

__all__ = ["main", "run"]


def _loop(
    env: gym.Env, steps: int, barrier: bool, policy: Callable | None = None
) -> tuple[float, float]:
    """(wall-clock, CPU-time) steps per second."""
    rng = np.random.default_rng(0)
    low, high = env.action_space.low, env.action_space.high
    actions = rng.uniform(low, high, size=(steps, *env.action_space.shape)).astype(np.float32)
    obs, _ = env.reset(seed=0)
    base = env.unwrapped
    for a in actions[: min(50, steps)]:  # warm caches
        env.step(a)
    obs, _ = env.reset(seed=0)
    t0, c0 = time.perf_counter(), time.process_time()
    for a in actions:
        if policy is not None:
            a = policy(obs)
        obs, _, term, trunc, _ = env.step(a)
        if barrier:
            base.barrier_terms("nominal")
            base.barrier_terms("true")
        if term or trunc:
            obs, _ = env.reset()
    return steps / (time.perf_counter() - t0), steps / (time.process_time() - c0)


def run(quick: bool = False, rounds: int | None = None) -> dict[str, float]:
    """Median steps per second over interleaved rounds (name -> float), and the median of the
    per-round ratios to Ant-v5 when it runs here.

    Every round runs every case once (``steps`` steps each), so slow phases of a shared
    machine hit all cases alike and the per-round ratios stay meaningful.
    """
    from afvsgp_gym.agents import NominalController

    steps = 300 if quick else 1000
    rounds = (2 if quick else 5) if rounds is None else int(rounds)
    static = "afvsgp_gym/FrankaObstacleStatic-v0"
    cases: list[tuple[str, gym.Env, bool, Callable | None]] = [
        ("point_mass", gym.make("afvsgp_gym/PointMassObstacle-v0"), True, None),
        ("franka_static_zero", gym.make(static), True, None),
        ("franka_dynamic_zero", gym.make("afvsgp_gym/FrankaObstacleDynamic-v0"), True, None),
        ("franka_static_kinematic", gym.make(static, nominal_model="kinematic"), True, None),
        ("franka_static_perturbed", gym.make(static, nominal_model="perturbed"), True, None),
        ("franka_static_exact", gym.make(static, nominal_model="exact"), True, None),
    ]
    loop_env = gym.make(static)
    cases.append(("franka_static_closed_loop", loop_env, True, NominalController(loop_env)))
    try:
        cases.append(("ant_v5", gym.make("Ant-v5"), False, None))
    except Exception:  # noqa: BLE001 - reference only; absent MuJoCo assets must not fail the run
        pass
    rates: dict[str, list[tuple[float, float]]] = {name: [] for name, *_ in cases}
    for _ in range(rounds):
        for name, env, barrier, policy in cases:
            rates[name].append(_loop(env, steps, barrier, policy))
    out: dict[str, float] = {}
    for name, rs in rates.items():
        arr = np.array(rs)
        out[f"{name}_steps_per_s_wall"] = float(np.median(arr[:, 0]))
        out[f"{name}_steps_per_s_cpu"] = float(np.median(arr[:, 1]))
    if "ant_v5" in rates:
        ant = np.array(rates["ant_v5"])
        for name in ("franka_static_zero", "franka_static_perturbed", "franka_static_closed_loop"):
            arr = np.array(rates[name])
            for k, clock in enumerate(("wall", "cpu")):
                out[f"{name}_over_ant_v5_{clock}"] = float(np.median(arr[:, k] / ant[:, k]))
    for _, env, *_ in cases:
        env.close()
    return out


def main(argv: list[str] | None = None) -> None:
    import argparse

    import mujoco

    parser = argparse.ArgumentParser(description="Franka env step rates against Ant-v5")
    parser.add_argument("--quick", action="store_true", help="fewer steps and rounds")
    res = run(quick=parser.parse_args(argv).quick)
    print(f"machine: {machine()}, mujoco {mujoco.__version__}, gymnasium {gym.__version__}")
    print(f"{'case':45s} {'value':>12s}")
    for k, v in res.items():
        print(f"{k:45s} {v:12.1f}" if v > 10 else f"{k:45s} {v:12.3f}")


if __name__ == "__main__":
    main()
