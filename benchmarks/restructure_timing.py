"""Per-step time of the filtered Franka step at two code trees, interleaved in one run.

The driver starts one worker process per (seed, learner, tree), alternating the trees
(A B A B ...), so machine drift hits both alike. Each worker imports ``afvsgp_gym`` from its
tree (``PYTHONPATH=tree``, checked), runs the nominal tracker behind ``SafetyFilter`` on the
static Franka scenario with the end-effector barrier only and nominal model "zero", and times
every step after ``--skip`` steps: the whole ``env.step`` of the wrapped env, the controller's
``filter`` + ``observe``, the inner env step (MuJoCo physics and env bookkeeping) and
``barrier_terms``.

    python benchmarks/restructure_timing.py --before ../wt-before --after . --json out.json
    python benchmarks/restructure_timing.py --profile ../wt-before --learners afvsgp
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import timeit
from pathlib import Path

import numpy as np

#: step: the wrapped env.step; ctrl: filter + observe; inner: the env under the wrapper (MuJoCo
#: and env bookkeeping); terms: barrier_terms called by the wrapper; other: step - ctrl - inner;
#: filter_on / filter_off: filter on the steps that needed the cone program / did not
#: (info filter_active).
PARTS = ("step", "ctrl", "filter", "observe", "inner", "terms", "other", "filter_on",
         "filter_off")
TIMED = PARTS[2:6]  # accumulated by the wrappers


def _timed(fn, acc: dict, key: str):
    """``fn`` adding its time to ``acc[key]``; calls made inside the inner step not counted."""
    def wrapper(*args, **kwargs):
        if acc["depth"]:
            return fn(*args, **kwargs)
        acc["depth"] += key == "inner"
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            acc[key] += time.perf_counter() - t0
            acc["depth"] -= key == "inner"

    return wrapper


def worker(learner: str, seed: int, steps: int, skip: int, profile: int, options: dict) -> dict:
    """One episode in this process: per-step times (us) of the steps after ``skip``, and
    per-call times (us, median of 7 x 200 calls) of the env's barrier code at the last state."""
    import gymnasium as gym

    import afvsgp_gym
    from afvsgp_gym.agents import NominalController
    from afvsgp_gym.envs.franka import FrankaObstacleEnv
    from afvsgp_gym.wrappers import SafetyFilter

    if learner in ("none", "oracle"):  # nothing to learn: they refuse learner_kwargs
        options = {k: v for k, v in options.items() if k != "learner_kwargs"}
    kwargs = {"nominal_model": "zero"}
    if "safety_spheres" in FrankaObstacleEnv._DEFAULTS:  # after a9edcaa: whole-arm default
        kwargs["safety_spheres"] = "ee"
    env = SafetyFilter(gym.make("afvsgp_gym/FrankaObstacleStatic-v0", **kwargs),
                       learner=learner, seed=seed, **options)
    agent = NominalController(env)
    ctrl, base = env.controller, env.unwrapped
    acc = dict.fromkeys(TIMED, 0.0) | {"depth": 0}
    ctrl.filter = _timed(ctrl.filter, acc, "filter")
    ctrl.observe = _timed(ctrl.observe, acc, "observe")
    env.env.step = _timed(env.env.step, acc, "inner")
    base.barrier_terms = _timed(base.barrier_terms, acc, "terms")
    rec = {k: [] for k in PARTS}
    active = []
    prof = None
    obs, _ = env.reset(seed=seed)
    for t in range(steps):
        action = agent(obs)
        if t == skip and profile:
            import cProfile

            prof = cProfile.Profile()
            prof.enable()
        for k in TIMED:
            acc[k] = 0.0
        t0 = time.perf_counter()
        obs, _, terminated, truncated, info = env.step(action)
        dt = time.perf_counter() - t0
        if t >= skip:
            rec["step"].append(dt)
            rec["ctrl"].append(acc["filter"] + acc["observe"])
            for k in TIMED:
                rec[k].append(acc[k])
            rec["other"].append(dt - rec["ctrl"][-1] - acc["inner"])
            active.append(bool(info["filter_active"]))
        if terminated or truncated:
            obs, _ = env.reset()
    for k, on in (("filter_on", True), ("filter_off", False)):
        rec[k] = [f for f, a in zip(rec["filter"], active, strict=True) if a == on]
    if prof is not None:
        import pstats

        prof.disable()
        for key in ("tottime", "cumulative"):
            pstats.Stats(prof, stream=sys.stderr).sort_stats(key).print_stats(profile)
    del ctrl.filter, ctrl.observe, env.env.step, base.barrier_terms
    compute = getattr(base, "_compute_barriers", None) or base._compute_terms  # after / before
    calls = {"after_state_change": base._after_state_change,
             "terms_exact": lambda: compute("exact"), "terms_zero": lambda: compute("zero"),
             "safety_info": base._safety_info}
    if hasattr(env, "_true_margin"):
        calls["true_margin"] = lambda: env._true_margin(base, np.zeros(7))
    micro = {k: float(np.median(timeit.repeat(f, number=200, repeat=7))) / 200 * 1e6
             for k, f in calls.items()}
    return {"file": afvsgp_gym.__file__, "active": float(np.mean(active)), "micro": micro,
            **{k: (np.array(v) * 1e6).round(2).tolist() for k, v in rec.items()}}


def run_worker(tree: Path, learner: str, seed: int, args, options: dict, top: int = 0) -> dict:
    """Run ``worker`` in a fresh process that imports afvsgp_gym from ``tree`` (checked)."""
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", "--learners", learner,
           "--seeds", str(seed), "--steps", str(args.steps), "--skip", str(args.skip),
           "--top", str(top), "--options", json.dumps(options)]
    env = {**os.environ, "PYTHONPATH": str(tree.resolve()), "OPENBLAS_NUM_THREADS": "1",
           "OMP_NUM_THREADS": "1"}
    out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(f"worker failed at {tree}:\n{out.stderr}")
    if top:
        print(out.stderr)
    res = json.loads(out.stdout)
    if not Path(res["file"]).resolve().is_relative_to(tree.resolve()):
        raise RuntimeError(f"afvsgp_gym came from {res['file']}, not {tree}")
    return res


def stats(x) -> dict:
    x = np.asarray(x)
    if not x.size:  # e.g. no step needed the cone program
        return {"median": float("nan"), "p99": float("nan"), "n": 0}
    return {"median": float(np.median(x)), "p99": float(np.percentile(x, 99)), "n": len(x)}


def commit(tree: Path) -> str:
    git = ["git", "-C", str(tree)]
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True, check=True).stdout.strip()
    dirty = subprocess.run([*git, "status", "--porcelain", "afvsgp_gym"], capture_output=True,
                           text=True, check=True).stdout.strip()
    return head + ("+dirty" if dirty else "")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", type=Path, help="tree of the old code")
    p.add_argument("--after", type=Path, help="tree of the new code")
    p.add_argument("--matched", type=json.loads, metavar="JSON",
                   help="also run the new code with these SafetyFilter options (e.g. the old "
                        "defaults) as a third variant")
    p.add_argument("--learners", nargs="+", default=["afvsgp", "oracle"])
    p.add_argument("--seeds", nargs="+", type=int, default=list(range(8)))
    p.add_argument("--steps", type=int, default=4000, help="steps per episode")
    p.add_argument("--skip", type=int, default=500, help="warm-up steps not timed")
    p.add_argument("--json", type=Path, help="write the summary here")
    p.add_argument("--profile", type=Path, help="cProfile one worker of this tree, then stop")
    p.add_argument("--top", type=int, default=0,
                   help="functions the profile prints (default 40; 0 in --worker: no profile)")
    p.add_argument("--options", type=json.loads, default={}, metavar="JSON",
                   help="SafetyFilter options of the --profile run")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.learners[0], args.seeds[0], args.steps, args.skip,
                                args.top, args.options)))
        return
    if args.profile:
        res = run_worker(args.profile, args.learners[0], args.seeds[0], args, args.options,
                         args.top or 40)
        print(f"{commit(args.profile)} {args.learners[0]} seed {args.seeds[0]}: "
              f"step median {np.median(res['step']):.1f} us (profiler on)")
        return
    if args.before is None or args.after is None:
        p.error("--before and --after are needed (or --profile TREE)")
    variants = {"before": (args.before, {}), "after": (args.after, {})}
    if args.matched is not None:
        variants["matched"] = (args.after, args.matched)
    pooled = {(c, lrn): {k: [] for k in PARTS} for c in variants for lrn in args.learners}
    micro = {(c, lrn): [] for c in variants for lrn in args.learners}
    episodes = []
    for seed in args.seeds:
        for lrn in args.learners:
            for code, (tree, options) in variants.items():  # A B A B: drift hits all alike
                res = run_worker(tree, lrn, seed, args, options)
                for k in PARTS:
                    pooled[code, lrn][k] += res[k]
                micro[code, lrn].append(res["micro"])
                ep = {"code": code, "learner": lrn, "seed": seed, "active": res["active"],
                      **{k: stats(res[k])["median"] for k in PARTS}}
                episodes.append(ep)
                print(json.dumps(ep), flush=True)
    summary = {"commits": {c: commit(t) for c, (t, _) in variants.items()},
               "matched": args.matched, "steps": args.steps, "skip": args.skip,
               "seeds": args.seeds, "episodes": episodes,
               "pooled": {f"{c}/{lrn}": {k: stats(v[k]) for k in PARTS}
                          for (c, lrn), v in pooled.items()},
               "micro_us": {f"{c}/{lrn}": {k: float(np.median([m[k] for m in v])) for k in v[0]}
                            for (c, lrn), v in micro.items()}}
    print("learner  part     " + "".join(f"{c:>20s}" for c in variants) + "  after/before")
    for lrn in args.learners:
        for k in PARTS:
            row = [summary["pooled"][f"{c}/{lrn}"][k] for c in variants]
            print(f"{lrn:8s} {k:8s} " + "".join(f"{r['median']:9.1f} /{r['p99']:8.1f}"
                                                for r in row)
                  + f"  {row[1]['median'] / row[0]['median']:5.2f} /"
                    f"{row[1]['p99'] / row[0]['p99']:5.2f}")
    for key, m in summary["micro_us"].items():
        print(key, {k: round(v, 1) for k, v in m.items()})
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
