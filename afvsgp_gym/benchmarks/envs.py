"""Environment speed on one core: env steps per second, barrier terms included.

Each figure is ``steps / wall time`` of a loop that calls ``env.step(a)`` and then
``env.unwrapped.barrier_terms("nominal")`` and ``barrier_terms("true")`` (what the safety
filter and its evaluation read every step; ``step`` itself computes both to report
``info["delta_b_true"]``). Actions are pre-drawn uniform samples; episodes are reset when they
end (reset time included). Gymnasium's ``Ant-v5`` (plain ``env.step``) is measured in the same
run as a reference point when it can be made. "closed loop" adds the NominalController.
Rates are given per wall-clock second and per CPU second of this process (the latter is the
meaningful one on a shared machine; everything runs in one thread).

Run: ``python -m afvsgp_gym.benchmarks.envs [--quick]``.
"""

from __future__ import annotations

import os
import platform
import sys
import time
from collections.abc import Callable

import gymnasium as gym
import numpy as np

import afvsgp_gym  # noqa: F401  (registers the ids)

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


def run(quick: bool = False) -> dict[str, float]:
    """Steps per second (name -> float) and ratios to Ant-v5 when it runs here."""
    from afvsgp_gym.agents import NominalController

    steps = 500 if quick else 5000
    out: dict[str, float] = {}
    cases = [
        ("point_mass", "afvsgp_gym/PointMassObstacle-v0", {}),
        ("franka_static_zero", "afvsgp_gym/FrankaObstacleStatic-v0", {}),
        ("franka_dynamic_zero", "afvsgp_gym/FrankaObstacleDynamic-v0", {}),
        (
            "franka_static_kinematic",
            "afvsgp_gym/FrankaObstacleStatic-v0",
            {"nominal_model": "kinematic"},
        ),
        (
            "franka_static_perturbed",
            "afvsgp_gym/FrankaObstacleStatic-v0",
            {"nominal_model": "perturbed"},
        ),
        ("franka_static_exact", "afvsgp_gym/FrankaObstacleStatic-v0", {"nominal_model": "exact"}),
    ]
    for name, env_id, kwargs in cases:
        env = gym.make(env_id, **kwargs)
        _put(out, name, _loop(env, steps, barrier=True))
        env.close()
    env = gym.make("afvsgp_gym/FrankaObstacleStatic-v0")
    _put(out, "franka_static_closed_loop", _loop(env, steps, True, NominalController(env)))
    env.close()
    try:
        ant = gym.make("Ant-v5")
    except Exception:  # noqa: BLE001 - reference only; absent MuJoCo assets must not fail the run
        ant = None
    if ant is not None:
        _put(out, "ant_v5", _loop(ant, steps, barrier=False))
        ant.close()
        for clock in ("wall", "cpu"):
            out[f"franka_static_zero_over_ant_v5_{clock}"] = (
                out[f"franka_static_zero_steps_per_s_{clock}"] / out[f"ant_v5_steps_per_s_{clock}"]
            )
    return out


def _put(out: dict[str, float], name: str, rates: tuple[float, float]) -> None:
    out[f"{name}_steps_per_s_wall"], out[f"{name}_steps_per_s_cpu"] = rates


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    import mujoco

    res = run(quick="--quick" in argv)
    print(f"machine: {machine()}, mujoco {mujoco.__version__}, gymnasium {gym.__version__}")
    print(f"{'case':45s} {'value':>12s}")
    for k, v in res.items():
        print(f"{k:45s} {v:12.1f}" if v > 10 else f"{k:45s} {v:12.3f}")


if __name__ == "__main__":
    main()
