"""GP learner speed at the paper's size (M=20, P=200, b=20, m=7), all figures from one run.

Times are CPU time of the benchmark thread (``time.thread_time_ns``: what one core spends,
unaffected by other processes on a shared machine); ``afvsgp_step_wall_*`` is wall-clock.

- AFVSGP: per-``predict_affine`` (one point, as the filter calls it), per-update and per-step
  median / p99; speed-up over recomputing the same weighted posterior in batch from the
  window; flatness: median step time late in the stream over early. The main loop is the
  filter's step: ``predict_affine(xi_t[None])`` at the current state, then ``update`` with the
  eq. 48 sample, whose feature is the midpoint ``(xi_t + xi_{t+1}) / 2``
  (afvsgp_gym/cbf/measurement.py), a different point, so the update computes its own kernel
  row. The learner is an ``AFVSGPBank`` of one (the filter stacks one per barrier).
- VSGP with N=2000 samples seen (O(N M^2) refresh per update) and SOGP (Bui 2017, default
  batch size): per-update median / p99 (updates at the eq. 48 midpoints).

The stream is a synthetic robot-like one: a 3-D periodic latent state embedded in b=20
features, m=7 actions, dB = sin(2 s0) + 0.3 sum_j u_j cos(s1 + j) + noise. BLAS runs on one
thread during the measurement (OpenBLAS threads only add jitter at these sizes).

Run: ``python -m afvsgp_gym.benchmarks.gp [--quick]`` (or ``afvsgp-gym bench --only gp``);
what it measures: docs/performance.md, "Other benchmarks".
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import platform
import time

import numpy as np
from scipy.linalg import cho_solve

from afvsgp_gym.gp import AFVSGP, SOGP, VSGP
from afvsgp_gym.gp._linalg import jittered_cholesky, ubar

__all__ = ["main", "run"]

B, M_ACT, M_IND, WINDOW = 20, 7, 20, 200


@contextlib.contextmanager
def _one_blas_thread():
    """Set OpenBLAS (numpy's and scipy's copies) to one thread; restore afterwards."""
    handles = []
    try:
        with open("/proc/self/maps") as fh:
            paths = {line.split()[-1] for line in fh if "openblas" in line}
    except OSError:
        paths = set()
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for suffix in ("64_", ""):
            get = getattr(lib, f"scipy_openblas_get_num_threads{suffix}", None)
            set_ = getattr(lib, f"scipy_openblas_set_num_threads{suffix}", None)
            if get is not None and set_ is not None:
                handles.append((set_, get()))
                set_(1)
                break
    try:
        yield bool(handles)
    finally:
        for set_, n in handles:
            set_(n)


def make_stream(n: int, seed: int = 0):
    """Synthetic stream (xi (n, 20), u (n, 7), z (n,)) with a periodic 3-D latent state."""
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    s = np.stack([np.sin(0.011 * t), np.cos(0.017 * t), np.sin(0.005 * t + 1.0)], axis=1)
    s += 0.05 * rng.normal(size=s.shape)
    w = rng.normal(size=(3, B))
    xi = np.tanh(s @ w + 0.1 * rng.normal(size=B))
    u = np.clip(0.5 * np.sin(0.02 * t[:, None] + np.arange(M_ACT)) + 0.3 * rng.normal(
        size=(n, M_ACT)), -1.0, 1.0)
    z = (np.sin(2.0 * s[:, 0]) + 0.3 * np.sum(u * np.cos(s[:, 1:2] + np.arange(M_ACT)), axis=1)
         + 0.05 * rng.normal(size=n))
    return xi, u, z


def _batch_posterior(gp: AFVSGP, xq: np.ndarray):
    """The same weighted Titsias posterior recomputed from the window (eq. 20), then one
    affine prediction: what a non-recursive implementation pays per step."""
    k = gp.kernel_
    xw, uw, zw, w = gp.window_samples()
    uw = ubar(uw)
    xo, uo = gp.inducing_xi_, ubar(gp.inducing_u_)
    koo = k._gram(xo, uo)
    koo[np.diag_indices_from(koo)] += gp.jitter_
    kxo = k._gram(xw, uw, xo, uo)
    s2 = gp.noise_variance_
    l_oo = jittered_cholesky(koo)
    sig = koo + (kxo.T * w) @ kxo / s2
    l_s = jittered_cholesky(sig)
    eye = np.eye(len(xo))
    bmat = cho_solve((l_s, True), eye, check_finite=False)
    d = cho_solve((l_oo, True), eye, check_finite=False) - bmat
    wv = bmat @ (kxo.T @ (w * zw)) / s2
    kt = k._cross_affine(xq, xo, uo)[0]
    return kt @ wv, np.diag(k._var) - kt @ d @ kt.T


def _stats(prefix: str, times, out: dict) -> None:
    arr = np.asarray(times)
    out[f"{prefix}_median_s"] = float(np.median(arr))
    out[f"{prefix}_p99_s"] = float(np.percentile(arr, 99))


def run(quick: bool = False) -> dict:
    """All figures in seconds (``*_s``) or ratios; see the module docstring."""
    n_stream = 10_000 if quick else 100_000
    n_early = n_stream // 10
    out: dict[str, float] = {}
    xi, u, z = make_stream(WINDOW + n_stream + 10, seed=0)
    with _one_blas_thread() as single:
        out["blas_single_thread"] = float(single)
        t0 = time.perf_counter()
        gp = AFVSGP(num_inducing=M_IND, window=WINDOW, forgetting=0.99,
                    max_iter=60 if quick else 200)
        gp.fit(xi[:WINDOW], u[:WINDOW], z[:WINDOW])
        out["afvsgp_fit_s"] = time.perf_counter() - t0
        upd = np.empty(n_stream)
        pred = np.empty(n_stream)
        wall = np.empty(n_stream)
        clock = time.thread_time_ns  # CPU time of this thread: one core, robust to load
        wclock = time.perf_counter
        mark = n_stream - n_early
        added_at_mark = 0
        mid = 0.5 * (xi[:-1] + xi[1:])  # eq. 48 midpoints
        for i in range(n_stream):
            if i == mark:
                added_at_mark = gp.n_added_
            j = WINDOW + i
            xq = xi[j:j + 1]
            w0 = wclock()
            t0 = clock()
            gp.predict_affine(xq)  # the filter: predict at the current state ...
            t1 = clock()
            gp.update(mid[j], u[j], z[j])  # ... and learn from the midpoint sample
            t2 = clock()
            wall[i] = wclock() - w0
            pred[i] = t1 - t0
            upd[i] = t2 - t1
        upd *= 1e-9
        pred *= 1e-9
        step = upd + pred
        _stats("afvsgp_predict_affine", pred, out)
        _stats("afvsgp_update", upd, out)
        _stats("afvsgp_step", step, out)
        _stats("afvsgp_step_wall", wall, out)
        out["afvsgp_inducing_changes_per_1k_updates"] = 1e3 * gp.n_added_ / n_stream
        out["afvsgp_inducing_changes_last_10pct_per_1k"] = (
            1e3 * (gp.n_added_ - added_at_mark) / n_early)
        span = min(2000, n_early // 2)
        early = float(np.median(step[n_early - span:n_early]))
        late = float(np.median(step[-span:]))
        out[f"afvsgp_step_median_at_{n_early}_s"] = early
        out[f"afvsgp_step_median_at_{n_stream}_s"] = late
        out["afvsgp_flatness_ratio"] = late / early
        # inducing-set events: a stream from a new region of the feature space (drift)
        xd, ud, zd = make_stream(3000, seed=2)
        xd = np.tanh(2.0 * xd + 0.5)
        ev, quiet = [], []
        for i in range(len(zd) - 1):
            before = gp.n_added_
            t0 = clock()
            gp.predict_affine(xd[i:i + 1])
            gp.update(0.5 * (xd[i] + xd[i + 1]), ud[i], zd[i])
            dt = (clock() - t0) * 1e-9
            (ev if gp.n_added_ != before else quiet).append(dt)
        out["afvsgp_drift_inducing_events"] = float(len(ev))
        if ev:
            _stats("afvsgp_step_with_inducing_event", ev, out)
        _stats("afvsgp_step_drift_no_event", quiet, out)
        # batch recompute of the same posterior
        xq = xi[-1:]
        reps = 200 if quick else 1000
        bt = []
        for _ in range(reps):
            t0 = clock()
            _batch_posterior(gp, xq)
            bt.append((clock() - t0) * 1e-9)
        out["batch_recompute_median_s"] = float(np.median(bt))
        out["afvsgp_speedup_vs_batch"] = out["batch_recompute_median_s"] / out[
            "afvsgp_step_median_s"]
        # VSGP with N = 2000 samples seen
        n_v = 2000
        xv, uv, zv = make_stream(n_v + 501, seed=1)
        vs = VSGP(gp.kernel_, gp.noise_variance_, num_inducing=M_IND)
        vs.fit(xv[:n_v], uv[:n_v], zv[:n_v], learn_hyperparameters=False)
        vt = []
        for i in range(n_v, n_v + (100 if quick else 500)):
            t0 = clock()
            vs.update(0.5 * (xv[i] + xv[i + 1]), uv[i], zv[i])
            vt.append((clock() - t0) * 1e-9)
        _stats("vsgp2000_update", vt, out)
        # SOGP (Bui 2017), default batch size
        so = SOGP(gp.kernel_, gp.noise_variance_, num_inducing=M_IND)
        so.fit(xv[:WINDOW], uv[:WINDOW], zv[:WINDOW], learn_hyperparameters=False)
        st, sp = [], []
        for i in range(WINDOW, WINDOW + (300 if quick else 2000)):
            t0 = clock()
            so.predict_affine(xv[i:i + 1])
            t1 = clock()
            so.update(0.5 * (xv[i] + xv[i + 1]), uv[i], zv[i])
            t2 = clock()
            sp.append((t1 - t0) * 1e-9)
            st.append((t2 - t1) * 1e-9)
        _stats("sogp_update", st, out)
        out["sogp_update_mean_s"] = float(np.mean(st))
        out["sogp_batch_size"] = float(so.batch_size)
        _stats("sogp_predict_affine", sp, out)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1e4 streamed updates, not 1e5")
    quick = parser.parse_args(argv).quick
    t0 = time.perf_counter()
    res = run(quick=quick)
    print(f"GP benchmark ({'quick' if quick else 'full'}), M={M_IND}, P={WINDOW}, b={B}, "
          f"m={M_ACT}; {platform.processor() or platform.machine()}, "
          f"python {platform.python_version()}, {time.perf_counter() - t0:.1f} s total")
    width = max(len(k) for k in res)
    for key, val in res.items():
        if key.endswith("_s"):
            print(f"  {key:<{width}}  {val * 1e6:10.1f} us")
        else:
            print(f"  {key:<{width}}  {val:10.3f}")


if __name__ == "__main__":
    main()
