"""Where the learned band misses, and what the model-side remedies do (docs/calibration.md).

Seeded 16 s episodes of the Franka scenes, nothing known (``nominal_model="zero"``), the
nominal tracker behind the whole-arm AFVSGP filter with the paper's band
(``calibration="off"``). For every (barrier, step) pair of the cone program the script keeps
the score ``e = (z - mean - bias) / std`` of the step's eq. 48 sample (the filter's own
bookkeeping, :attr:`SafetyController.last_calibration`), and splits the misses ``e < -beta``:

- by the barrier's kind: an obstacle pair (sphere, obstacle), a joint range or a joint speed;
- by whether the pair's constraint was binding at the applied action (its margin in the cone
  program below 1e-3) or slack;
- by the half of the episode after warm-up.

Two model-side remedies of issue 43, against the same seeds:

- ``noise``: the band of the eq. 48 *sample* rather than of the latent model error, ``std``
  replaced by ``sqrt(std^2 + s2)`` (``s2`` the learner's noise variance), counted on the same
  steps (the filter's actions unchanged);
- ``refit``: the hyperparameters re-fitted on the learners' windows
  (:meth:`AFVSGPBank.window_samples`) whenever the miss rate of the last 2000 scored pairs
  exceeds 3 x ``Phi(-beta)``, at most once per 500 steps (its own episodes: the refits change
  the actions); the wall time of the refits is reported.

    python benchmarks/calibration_anatomy.py [--seeds 3] [--json PATH]

(default ``benchmarks/results/calibration_anatomy.json``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import afvsgp_gym  # noqa: F401  (registers the envs)
from afvsgp_gym.agents import NominalController
from afvsgp_gym.cbf.calibration import miss_target
from afvsgp_gym.cbf.learners import AFVSGPLearnerBank
from afvsgp_gym.evaluation import code_version, cpu_model
from afvsgp_gym.wrappers import SafetyFilter

SCENES = ("Static", "Dynamic", "Random")
BINDING = 1e-3
DRIFT_WINDOW, DRIFT_FACTOR, REFIT_GAP = 2000, 3.0, 500


def _kind(name: str) -> str:
    if "/obstacle" in name:
        return "obstacle"
    return "speed" if "speed" in name else "range"


def _learner_bank(bank):
    """The AFVSGP learner bank under the controller's barrier-level views, and the
    hyperparameter groups its fit takes."""
    groups = None
    while not isinstance(bank, AFVSGPLearnerBank):
        layout = getattr(bank, "layout", None)
        groups = layout.group if layout is not None else getattr(bank, "groups", groups)
        bank = bank.bank
    return bank, groups


def _refit(ctl) -> float:
    """Re-fit every learner on its window; returns the wall time."""
    lb, groups = _learner_bank(ctl.bank)
    data = [lb.bank.window_samples(k) for k in range(lb.bank.n_learners)]
    t0 = time.perf_counter()
    lb.fit(data, ctl.config.learn_hyperparameters, groups)
    return time.perf_counter() - t0


def episode(scene: str, seed: int, refit: bool) -> dict:
    env = SafetyFilter(gym.make(f"afvsgp_gym/FrankaObstacle{scene}-v0", nominal_model="zero"),
                       learner="afvsgp", calibration="off")
    policy = NominalController(env)
    obs, info = env.reset(seed=seed)
    ctl = env.controller
    beta = ctl.config.beta
    alpha = miss_target(beta)
    kinds = np.array([_kind(n) for n in env.unwrapped.barrier_names])
    held = {}
    filt = ctl.filter

    def keep(*a, **k):  # the filter's result: each barrier's margin at the applied action
        held["res"] = res = filt(*a, **k)
        return res

    ctl.filter = keep
    rows_out, recent, refits, refit_s, last_refit, first = [], [], 0, 0.0, -REFIT_GAP, None
    cost = 0
    for t in range(4000):
        obs, _, term, trunc, info = env.step(policy(obs))
        cost += info["cost"] > 0
        scored = ctl._scored
        if scored is not None:
            z, center, std = scored[:3]
            rows = np.flatnonzero(np.isfinite(info["delta_b_std"]))
            e = (z - center) / std
            noise = np.sqrt(ctl.bank.noise_variance(rows))
            margins = held["res"].margins[rows]
            first = t if first is None else first
            for k, r in enumerate(rows):
                if np.isfinite(e[k]):
                    rows_out.append((t, kinds[r], e[k], e[k] * std[k] / np.hypot(std[k], noise[k]),
                                     margins[k] < BINDING))
            recent.extend((e[np.isfinite(e)] < -beta).tolist())
            recent = recent[-DRIFT_WINDOW:]
        if (refit and len(recent) >= DRIFT_WINDOW and t - last_refit >= REFIT_GAP
                and np.mean(recent) > DRIFT_FACTOR * alpha):
            refit_s += _refit(ctl)
            refits, last_refit, recent = refits + 1, t, []
        if term or trunc:
            break
    env.close()
    half = (first + t) / 2 if first is not None else 0
    out = {"scene": scene, "seed": seed, "refit": refit, "steps": t + 1,
           "cost_steps": int(cost), "refits": refits, "refit_seconds": refit_s,
           "beta": float(beta), "counts": {}}
    for t_, kind, e, e_noise, binding in rows_out:
        late = "late" if t_ > half else "early"
        for key in (f"kind={kind}", f"binding={binding}", f"half={late}", "all"):
            c = out["counts"].setdefault(key, [0, 0, 0])
            c[0] += 1
            c[1] += int(e < -beta)
            c[2] += int(e_noise < -beta)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--json", type=Path,
                    default=Path(__file__).parent / "results" / "calibration_anatomy.json")
    args = ap.parse_args()
    code = code_version()  # the code that runs, read before any later edit of the tree
    t0 = time.perf_counter()
    episodes = [episode(sc, 300 + s, refit) for refit in (False, True) for sc in SCENES
                for s in range(args.seeds)]
    res = {"episodes": episodes, "seconds": time.perf_counter() - t0, "machine": cpu_model(),
           "date": time.strftime("%Y-%m-%d"), "code": code,
           "settings": {"binding": BINDING, "drift_window": DRIFT_WINDOW,
                        "drift_factor": DRIFT_FACTOR, "refit_gap": REFIT_GAP}}
    args.json.write_text(json.dumps(res, indent=1) + "\n")
    print(f"wrote {args.json} ({res['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
