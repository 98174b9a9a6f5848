"""Table I's prediction stream with the noise-variance floor of the hyperparameter fit at two
values (benchmarks/gp.md, "Noise floor").

    python benchmarks/noise_floor.py            # floors 1e-6 and 1e-4, about 1 min

Records the stream of ``afvsgp-gym reproduce`` (oracle-filtered static scenario, y -> z switch),
fits AFVSGP, VSGP and SOGP as the filter fits them with ``hyper.NOISE_MIN`` set to each floor,
then predicts and updates over the stream; prints the fitted noise, the MSE (stream, after the
switch), the largest and the median error after the switch, and the share of steps whose error
exceeds 3 predicted standard deviations.
"""

from __future__ import annotations

import argparse

import numpy as np

import afvsgp_gym  # noqa: F401  (registers the ids)
from afvsgp_gym import reproduce as rep
from afvsgp_gym.gp import hyper


def streams(cfg: rep.ReproduceConfig) -> tuple[dict, dict]:
    """The training (y motion) and evaluation (y -> z switch) streams of ``reproduce``."""
    kw = dict(cfg.env_kwargs)
    start = rep._default_start(cfg.static_env, kw)
    train = rep._slice(rep._record(cfg.static_env, {**kw, "switch_time": 1e6}, cfg.seed,
                                   start + cfg.n_offline), start, start + cfg.n_offline)
    stream = rep._slice(rep._record(cfg.static_env, kw, cfg.seed + 1, 10**9), start, 10**9)
    return train, stream


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--floors", default="1e-6,1e-4", help="comma-separated NOISE_MIN values")
    args = parser.parse_args()
    cfg = rep.ReproduceConfig()
    train, stream = streams(cfg)
    after = stream["t"] >= float(stream["switch_time"])
    m = train["u"].shape[1]
    default = hyper.NOISE_MIN
    print("floor   learner  s2        mse     mse_after  max|e|  median|e|_after  >3std")
    try:
        for floor in (float(f) for f in args.floors.split(",")):
            hyper.NOISE_MIN = floor
            for name in ("afvsgp", "vsgp", "sogp"):
                n = cfg.n_prelim if name == "afvsgp" else cfg.n_offline
                learner = rep._fit_learner(name, cfg, train["xi_mid"][:n], train["u"][:n],
                                           train["z"][:n], m)
                res = rep._predict_then_update(learner, stream, online=True)
                err = res["mean"] - stream["truth"]
                print(f"{floor:<7.0e} {name:<8} {learner.noise_variance_:<9.2e} "
                      f"{np.mean(err ** 2):<7.4f} {np.mean(err[after] ** 2):<10.4f} "
                      f"{np.abs(err).max():<7.2f} {np.median(np.abs(err[after])):<16.4f} "
                      f"{np.mean(np.abs(err) > 3 * res['std']):.3f}")
    finally:
        hyper.NOISE_MIN = default


if __name__ == "__main__":
    main()
