"""The cost of the obstacle estimator per control step (afvsgp_gym.cbf.estimation), against
filterpy's ``KalmanFilter`` (one 6-D filter per obstacle, the same constant-velocity model).

A 1 kHz control loop over a 30 Hz camera with 60 ms delay and 1 cm noise: each control step
hands the newest arrived sample to ``update`` (a repeat on most steps, which the estimator
skips) and asks ``predict`` for the estimate at the control time, as
:class:`~afvsgp_gym.wrappers.obstacle_tracking.ObstacleTracking` does. Timed per step with
``time.perf_counter`` (garbage collection off), split into *hold* steps (no new sample: the
prediction only) and *fuse* steps (a new sample fused, then the prediction), median and p99
in microseconds, for ``O = 1, 5, 25`` obstacles. filterpy, where importable (``pip install
filterpy``; not a dependency of the package), does per obstacle on a fuse step
``F, Q = ...; predict(); update(z)`` and on every step the pure prediction
``filterpy.kalman.predict(x, P, F_t, Q_t)``; its 6-D ``F``, ``Q`` (``kron`` of the per-axis
ones with ``I3``) are built once per step for all obstacles and counted in its time. Both
estimates are compared at the end (they must agree to rounding).

    OPENBLAS_NUM_THREADS=1 python benchmarks/estimator_speed.py [--seconds 10]

Writes ``benchmarks/results/estimator_speed.json`` (``--output``) with the figures, the CPU
model name (/proc/cpuinfo), and the Python, numpy (and filterpy) versions.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from afvsgp_gym.cbf.estimation import ObstacleEstimator, discrete_process_noise, transition
from afvsgp_gym.evaluation.version import cpu_model

MODEL = "constant-velocity"
SIGMA, PROCESS_STD, INITIAL_VELOCITY_STD = 0.01, 1.0, 0.5
RATE, DELAY, CONTROL = 30, 0.06, 1000       # camera Hz, camera latency s, control Hz


def _samples(n_obstacles: int, n_frames: int, seed: int) -> np.ndarray:
    """Camera samples (n_frames, O, 3) of obstacles moving at constant velocity."""
    rng = np.random.default_rng(seed)
    p0 = rng.uniform(-1, 1, (n_obstacles, 3))
    v = rng.normal(0, 0.3, (n_obstacles, 3))
    t = np.arange(n_frames)[:, None, None] / RATE
    return p0 + v * t + rng.normal(0, SIGMA, (n_frames, n_obstacles, 3))


def _schedule(steps: int) -> np.ndarray:
    """The newest sample index arrived by each control step (-1: none yet)."""
    j = np.arange(steps)
    return np.floor(np.round((j / CONTROL - DELAY) * RATE, 9)).astype(int)


def _stats(times: list[float]) -> dict[str, float]:
    us = np.asarray(times) * 1e6
    return {"median_us": round(float(np.median(us)), 2),
            "p99_us": round(float(np.percentile(us, 99)), 2), "steps": len(us)}


def time_ours(n_obstacles: int, steps: int, seed: int) -> tuple[dict, np.ndarray]:
    newest = _schedule(steps)
    z = _samples(n_obstacles, newest[-1] + 1, seed)
    est = ObstacleEstimator(n_obstacles, SIGMA, process_std=PROCESS_STD, model=MODEL,
                            initial_velocity_std=INITIAL_VELOCITY_STD)
    hold, fuse = [], []
    seen = -1
    gc.disable()
    try:
        for j in range(steps):
            k = newest[j]
            if k < 0:
                continue
            t = j / CONTROL
            t0 = time.perf_counter()
            est.update(z[k], k / RATE)
            out = est.predict(t)
            elapsed = time.perf_counter() - t0
            if seen >= 0:                   # the first sample only initialises
                (fuse if k > seen else hold).append(elapsed)
            seen = k
    finally:
        gc.enable()
    return {"hold": _stats(hold), "fuse": _stats(fuse), "all": _stats(hold + fuse)}, \
        np.concatenate(out[:2], axis=1)


def time_filterpy(n_obstacles: int, steps: int, seed: int) -> tuple[dict, np.ndarray]:
    from filterpy.kalman import KalmanFilter
    from filterpy.kalman import predict as kf_predict

    newest = _schedule(steps)
    z = _samples(n_obstacles, newest[-1] + 1, seed)
    eye = np.eye(3)
    filters = []
    for _ in range(n_obstacles):
        kf = KalmanFilter(dim_x=6, dim_z=3)
        kf.H = np.kron(np.eye(1, 2), eye)
        kf.R = SIGMA ** 2 * eye
        filters.append(kf)
    p0 = np.kron(np.diag([SIGMA ** 2, INITIAL_VELOCITY_STD ** 2]), eye)
    hold, fuse = [], []
    seen, last = -1, 0.0
    out = np.zeros((n_obstacles, 6))
    gc.disable()
    try:
        for j in range(steps):
            k = newest[j]
            if k < 0:
                continue
            t = j / CONTROL
            t0 = time.perf_counter()
            if k > seen:
                ts = k / RATE
                if seen < 0:
                    for i, kf in enumerate(filters):
                        kf.x = np.concatenate([z[k, i], np.zeros(3)])[:, None]
                        kf.P = p0.copy()
                else:
                    f6 = np.kron(transition(ts - last, MODEL), eye)
                    q6 = np.kron(discrete_process_noise(ts - last, PROCESS_STD, MODEL), eye)
                    for i, kf in enumerate(filters):
                        kf.F, kf.Q = f6, q6
                        kf.predict()
                        kf.update(z[k, i])
                last = ts
            f6 = np.kron(transition(t - last, MODEL), eye)
            q6 = np.kron(discrete_process_noise(t - last, PROCESS_STD, MODEL), eye)
            for i, kf in enumerate(filters):
                x, _p = kf_predict(kf.x, kf.P, f6, q6)
                out[i] = x[:, 0]
            elapsed = time.perf_counter() - t0
            if seen >= 0:
                (fuse if k > seen else hold).append(elapsed)
            seen = k
    finally:
        gc.enable()
    return {"hold": _stats(hold), "fuse": _stats(fuse), "all": _stats(hold + fuse)}, out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0,
                    help="simulated seconds of 1 kHz control per obstacle count")
    ap.add_argument("--obstacles", type=int, nargs="+", default=[1, 5, 25])
    ap.add_argument("--output", type=Path,
                    default=Path(__file__).resolve().parent / "results" / "estimator_speed.json")
    args = ap.parse_args(argv)
    try:
        import filterpy
        fp_version = filterpy.__version__
    except ImportError:
        fp_version = None
        print("filterpy is not installed: timing afvsgp_gym's estimator only "
              "(pip install filterpy for the comparison)")
    steps = int(args.seconds * CONTROL)
    time_ours(2, 200, 0)                                    # warm up
    rows = []
    for o in args.obstacles:
        ours, est_ours = time_ours(o, steps, o)
        row = {"obstacles": o, "ours": ours, "filterpy": None}
        if fp_version is not None:
            fp, est_fp = time_filterpy(o, steps, o)
            row["filterpy"] = fp
            row["max_abs_difference"] = float(np.max(np.abs(est_ours - est_fp)))
        rows.append(row)

    head = f"{'O':>3}  {'step':<5} {'ours median':>12} {'ours p99':>9}"
    if fp_version is not None:
        head += f" {'filterpy median':>16} {'filterpy p99':>13} {'ratio':>6}"
    print(f"update + predict per control step (us); {CONTROL} Hz control, {RATE} Hz camera")
    print(head)
    for row in rows:
        for kind in ("hold", "fuse"):
            ours = row["ours"][kind]
            line = (f"{row['obstacles']:>3}  {kind:<5} {ours['median_us']:>12.1f} "
                    f"{ours['p99_us']:>9.1f}")
            if row["filterpy"] is not None:
                fp = row["filterpy"][kind]
                line += (f" {fp['median_us']:>16.1f} {fp['p99_us']:>13.1f} "
                         f"{fp['median_us'] / ours['median_us']:>6.1f}")
            print(line)
    if fp_version is not None:
        diff = max(r["max_abs_difference"] for r in rows)
        print(f"largest difference of the final estimates (ours - filterpy): {diff:.1e}")

    result = {
        "machine": {"cpu": cpu_model(), "cores": os.cpu_count(),
                    "python": platform.python_version(), "numpy": np.__version__,
                    "filterpy": fp_version,
                    "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS")},
        "settings": {"model": MODEL, "measurement_std": SIGMA, "process_std": PROCESS_STD,
                     "camera_rate_hz": RATE, "camera_delay_s": DELAY,
                     "control_rate_hz": CONTROL, "seconds": args.seconds},
        "results": rows,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    with open(args.output, "w") as fh:
        json.dump(result, fh, indent=1)
    print(f"wrote {args.output}")
    return result


if __name__ == "__main__":
    main()
