"""Sweep throughput: Franka episodes per minute with 1 and 2 local workers, and Ray's overhead.

Workload: ``episodes`` Franka episodes (dynamic scenario, AFVSGP filter, nominal "zero",
``max_steps`` steps each, seeds 0..), run through :func:`afvsgp_gym.sweep.run_sweep` into a
fresh results file per case, exactly as ``afvsgp-gym sweep`` does. Cases run in interleaved
rounds (every case once per round) so load changes hit all alike; figures are medians over
rounds, the speed-up the median of the per-round ratios.

- Phase 1, ``pool1``/``pool2``: :class:`~afvsgp_gym.sweep.LocalExecutor` with 1 and 2
  workers, started and warmed (every worker has imported MuJoCo) before the clock starts; their
  start-up is timed apart (``pool_startup_s``).
- Phase 2 (when ray is installed), ``ray2`` against ``pool2``:
  :class:`~afvsgp_gym.sweep.RayExecutor` on a local Ray instance with 2 CPUs, warmed the same
  way; ``ray_init_s`` is ``ray.init``'s time.
- ``*_worker_cpu_share``: the episodes' CPU time per worker per wall second (1: every worker
  had a core of its own throughout); ``*_cpu_per_episode_s``: CPU seconds per episode (equal
  for 1 and 2 workers when running side by side costs nothing extra, e.g. no shared-cache or
  memory-bandwidth contention).
- ``*_other_busy_cores``: cores kept busy meanwhile by everything but the episodes (the
  machine's busy time from /proc/stat minus the episodes' CPU time, per wall second): the
  parent process, Ray's daemons, and other jobs on a shared machine. A speed-up is only
  meaningful when this stays well below 1.
- Overhead per episode of an executor over the 2-worker pool: ``(T_ray - T_pool2) * 2 / n``
  (worker-seconds per episode); and the dispatch cost alone, per task, from ``tasks`` trivial
  tasks (``_noop``) on each executor.

Run: ``python -m afvsgp_gym.benchmarks.sweep [--quick] [--rounds R] [--episodes N]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from afvsgp_gym.benchmarks._machine import machine

__all__ = ["main", "run"]

ENV = "afvsgp_gym/FrankaObstacleDynamic-v0"


def _noop(x: int) -> int:
    return x


def _warm(x: int) -> int:
    """Import what an episode imports (MuJoCo, the envs, the filter) in a worker."""
    import afvsgp_gym.envs.franka  # noqa: F401
    import afvsgp_gym.wrappers  # noqa: F401

    time.sleep(0.2)  # keep this worker busy so the next warm-up task goes to another one
    return x


def _episodes(n: int, max_steps: int):
    from afvsgp_gym.evaluation import EpisodeSpec

    return [("bench", EpisodeSpec(ENV, seed, learner="afvsgp", max_steps=max_steps))
            for seed in range(n)]


def _busy_cores_s() -> float:
    """Core-seconds the whole machine spent busy since boot (/proc/stat; NaN elsewhere)."""
    try:
        with open("/proc/stat") as fh:
            f = [int(x) for x in fh.readline().split()[1:]]
    except OSError:
        return float("nan")
    user, nice, system, _idle, _iowait, irq, softirq, steal = (f + [0] * 8)[:8]
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def _timed_sweep(executor, episodes, folder: Path, name: str) -> dict[str, float]:
    """One sweep: its wall seconds, the cores other processes kept busy meanwhile (the
    machine's busy core-seconds minus the episodes' own CPU time, per wall second) and the
    episodes' CPU time per worker per wall second (1: every worker had a core throughout)."""
    from afvsgp_gym.sweep import run_sweep

    path = folder / f"{name}.jsonl"
    path.unlink(missing_ok=True)
    b0, t0 = _busy_cores_s(), time.perf_counter()
    res = run_sweep(episodes, path, executor, progress=False)
    wall, busy = time.perf_counter() - t0, _busy_cores_s() - b0
    if res.ran != len(episodes) or res.failed:
        raise RuntimeError(f"{name}: {res.ran} of {len(episodes)} episodes ran")
    own = sum(r["cpu_s"] for r in res.records)
    return {"wall": wall, "other": (busy - own) / wall,
            "share": own / (wall * min(executor.workers, len(episodes))),
            "cpu": own / len(episodes)}


def _rounds(executors: dict, episodes, rounds: int, folder: Path) -> dict[str, list[dict]]:
    """Every executor once per round, interleaved."""
    out: dict[str, list[dict]] = {k: [] for k in executors}
    for _ in range(rounds):
        for name, ex in executors.items():
            out[name].append(_timed_sweep(ex, episodes, folder, f"{name}"))
    return out


def _median(runs: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in runs)


def _dispatch(executor, tasks: int) -> float:
    """Wall seconds per trivial task (submission, transfer, result) on a warm executor."""
    t0 = time.perf_counter()
    n = sum(1 for _ in executor.map_unordered(_noop, range(tasks)))
    assert n == tasks
    return (time.perf_counter() - t0) / tasks


def run(quick: bool = False, rounds: int | None = None, episodes: int | None = None,
        max_steps: int = 1000, tasks: int = 200) -> dict[str, float]:
    """Median figures over interleaved rounds (see the module docstring)."""
    from afvsgp_gym.sweep import InlineExecutor, LocalExecutor

    rounds = rounds or (1 if quick else 3)
    n = episodes or (4 if quick else 24)
    eps = _episodes(n, max_steps)
    try:
        import ray
    except ImportError:
        ray = None
    out: dict[str, float] = {"episodes": float(n), "max_steps": float(max_steps)}
    t0 = time.perf_counter()
    pools = {f"pool{w}": LocalExecutor(w) for w in (1, 2)}
    for pool in pools.values():
        list(pool.map_unordered(_warm, range(pool.workers)))
    out["pool_startup_s"] = (time.perf_counter() - t0) / 2
    try:
        with tempfile.TemporaryDirectory() as tmp:
            # phase 1: 1 against 2 local workers (no Ray daemons running)
            runs = _rounds(pools, eps, rounds, Path(tmp))
            for name, rr in runs.items():
                out[f"{name}_episodes_per_min"] = 60.0 * n / _median(rr, "wall")
                out[f"{name}_worker_cpu_share"] = _median(rr, "share")
                out[f"{name}_other_busy_cores"] = _median(rr, "other")
                out[f"{name}_cpu_per_episode_s"] = _median(rr, "cpu")
            out["speedup_2_over_1"] = statistics.median(
                a["wall"] / b["wall"] for a, b in zip(runs["pool1"], runs["pool2"], strict=True))
            out["inline_dispatch_per_task_s"] = _dispatch(InlineExecutor(), tasks)
            out["pool2_dispatch_per_task_s"] = _dispatch(pools["pool2"], tasks)
            # phase 2: Ray (2 CPUs) against the 2-worker pool
            if ray is not None:
                from afvsgp_gym.sweep import RayExecutor

                t0 = time.perf_counter()
                ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
                out["ray_init_s"] = time.perf_counter() - t0
                rex = RayExecutor()
                list(rex.map_unordered(_warm, range(4)))
                runs = _rounds({"pool2": pools["pool2"], "ray2": rex}, eps, rounds, Path(tmp))
                out["ray2_episodes_per_min"] = 60.0 * n / _median(runs["ray2"], "wall")
                out["ray2_worker_cpu_share"] = _median(runs["ray2"], "share")
                out["ray2_other_busy_cores"] = _median(runs["ray2"], "other")
                out["pool2_with_ray_up_episodes_per_min"] = (
                    60.0 * n / _median(runs["pool2"], "wall"))
                out["ray2_over_pool2_overhead_per_episode_s"] = statistics.median(
                    2.0 * (r["wall"] - p["wall"]) / n
                    for r, p in zip(runs["ray2"], runs["pool2"], strict=True))
                out["ray2_dispatch_per_task_s"] = _dispatch(rex, tasks)
    finally:
        for ex in pools.values():
            ex.close()
        if ray is not None and ray.is_initialized():
            ray.shutdown()
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 round of 4 episodes")
    parser.add_argument("--rounds", type=int, default=None)
    parser.add_argument("--episodes", type=int, default=None)
    parser.add_argument("--max-steps", type=int, default=1000)
    args = parser.parse_args(argv)
    print(f"sweep benchmark on {machine()}", flush=True)
    res = run(quick=args.quick, rounds=args.rounds, episodes=args.episodes,
              max_steps=args.max_steps)
    width = max(len(k) for k in res)
    for key, val in res.items():
        shown = f"{val * 1e3:10.3f} ms" if key.endswith("_task_s") else f"{val:10.4g}"
        print(f"{key:<{width}}  {shown}")


if __name__ == "__main__":
    main()
