"""Whole-arm filter timing: the filtered step against the number of barriers.

``python -m afvsgp_gym.benchmarks.arm [--quick] [--steps N] [--seeds S ...]`` runs the nominal
tracker behind ``SafetyFilter(learner)`` on the static Franka scenario (nominal "zero"; every
configuration here, and those of the benchmarks built on :class:`TimedEpisode`, without the
env's 93 self-collision barriers unless it says ``self_collision``: the counts are the arm's
pairs with obstacles): the default env (21 arm spheres and the 28 joint-limit barriers, 49 in
all, which share 21 + 7 learners), the same arm before the limits (the 21 obstacle pairs, the
linear class-K chain and the warm-up around the proposal: the price of the limits), and the
obstacle pairs alone with 1, 7, 21 and 42 barriers (the end-effector sphere; the 7 hand spheres;
the 21 arm spheres; the arm with a second obstacle), each with the env's suggested settings
(AFVSGP with M = 30, P = 500 on several spheres, the method's M = 40, P = 1000 on one), plus the
end-effector sphere at the whole-arm settings (K = 21 against K = 1 at equal settings) and the
arm at the method's, and times, per control step after the warm-up, with ``perf_counter``:

- ``step``: the filter's own work, ``SafetyController.filter`` (constraints, the learners'
  predictions for the barriers in the program, the cone program) plus
  ``SafetyController.observe`` (eq. 48 and every learner's update): the path a robot loop runs;
- ``learners``: the part of it spent in the learner bank (``predict_affine`` + ``update``),
  and its two parts: ``update`` (every learner, every step) and the prediction time per
  barrier predicted (only the barriers in the program are: their number is the scenario's
  geometry, not the bank's batching);
- ``fit``: the end-of-warm-up hyperparameter fit of all K learners (CPU seconds);
- ``env.step``: the whole wrapped step the user calls (the physics, the env's barrier terms,
  the filter and the learning).

Everything runs in one process. The configurations' episodes of one seed advance one control
step each in turn (lockstep), so that a drift of the machine's speed, up to 2x within minutes
on the VMs measured, hits all of them alike and the ratios are measured on the same seconds;
each step then finds the caches warmed by the other configurations, which makes absolute
times somewhat higher than a configuration alone (``--sequential`` runs them one after
another). Pin the process to one core (``taskset -c 0``) with
``OPENBLAS_NUM_THREADS=1``.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from afvsgp_gym._compiled import resolve
from afvsgp_gym.benchmarks._machine import calibration_line, machine
from afvsgp_gym.cbf.learners import REGISTRY
from afvsgp_gym.envs.franka import FrankaObstacleEnv as FrankaEnv

#: the env every configuration runs on unless told otherwise
ENV_ID = "afvsgp_gym/FrankaObstacleStatic-v0"

#: AFVSGP's settings on the whole arm (the Franka envs' suggestion) and the method's own
#: (the learner registry's, which the end-effector sphere keeps)
ARM_LEARNER = dict(FrankaEnv.ARM_LEARNER_DEFAULTS["afvsgp"])
METHOD_LEARNER = {k: REGISTRY["afvsgp"].default_kwargs[k] for k in ARM_LEARNER}

#: name -> env kwargs; "filter": SafetyFilter options on top of the env's suggestions;
#: "fast_path": False turns the solver's certified fast path off, so every cone program goes
#: to clarabel (the step without what the fast path saves); the "numpy" rows run the cone
#: program, the learners or everything (the backend "numpy": no compiled code) in numpy
#: the filter as it was before the joint-limit barriers: the obstacle pairs only, the linear
#: class-K chain, the warm-up around the proposal with the method's noise
BEFORE_LIMITS: dict[str, Any] = {"limit_barriers": False, "filter": {
    "braking_deceleration": float("inf"), "warmup_exploration": "proposal",
    "exploration_noise": 0.3}}

CONFIGS: dict[str, dict[str, Any]] = {
    "1 (ee)": {"safety_spheres": "ee", "limit_barriers": False},
    "1 (ee), arm settings": {"safety_spheres": "ee", "limit_barriers": False,
                             "filter": {"learner_kwargs": ARM_LEARNER}},
    "7 (hand)": {"safety_spheres": "hand", "limit_barriers": False},
    "21 (arm)": {},
    "21 (arm), before the limits": BEFORE_LIMITS,
    "21 (arm), method settings": {"filter": {"learner_kwargs": METHOD_LEARNER}},
    "21 (arm), clarabel only": {"fast_path": False},
    "21 (arm), numpy solver": {"filter": {"backend": resolve("auto", ("step", "bank"))}},
    "21 (arm), numpy learners": {"filter": {"backend": resolve("auto", ("cones", "step"))}},
    "21 (arm), numpy only": {"filter": {"backend": "numpy"}},
    "42 (arm, 2 obstacles)": {"obstacles": "two", "limit_barriers": False},
}


def _env_kwargs(spec: dict[str, Any]) -> dict[str, Any]:
    from afvsgp_gym.envs.safety_spheres import PANDA_ARM_SPHERES

    kw = dict(spec)
    kw.setdefault("self_collision", False)  # the barriers counted: the arm's with obstacles
    for key in ("fast_path", "filter", "learner"):
        kw.pop(key, None)
    if kw.get("safety_spheres") == "hand":
        kw["safety_spheres"] = list(PANDA_ARM_SPHERES[14:])
    if isinstance(kw.get("obstacles"), str) and kw["obstacles"] == "two":
        # the static scenario's sphere and a second one below the other side of the path
        kw["obstacles"] = [
            {"position": [0.307, 0.20, 0.417], "radius": 0.05},
            {"position": [0.307, -0.20, 0.417], "radius": 0.05},
        ]
    return kw


class TimedEpisode:
    """One filtered episode prefix of configuration ``spec`` (env kwargs, SafetyFilter
    options under ``"filter"``, and a ``"learner"`` of its own over ``learner``) on ``env_id``
    whose filter is timed per control step (see the module docstring): the env's
    ``warmup_steps`` plus ``steps`` control steps, timed from the step after the one whose
    update fits the learners; :meth:`step` advances it by one step."""

    def __init__(self, spec: dict[str, Any], learner: str = "afvsgp", steps: int = 1500,
                 seed: int = 0, env_id: str = ENV_ID):
        import gymnasium as gym

        import afvsgp_gym  # noqa: F401
        from afvsgp_gym.agents import NominalController
        from afvsgp_gym.wrappers import SafetyFilter

        self.env = env = SafetyFilter(gym.make(env_id, **_env_kwargs(spec)),
                                      learner=spec.get("learner", learner), seed=seed,
                                      **spec.get("filter", {}))
        ctrl, bank = env.controller, env.controller.bank
        ctrl.prepare_programs()  # as a real-time loop would: no solver built while timed
        ctrl.socp.fast_path = bool(spec.get("fast_path", True))
        clock = dict.fromkeys(("learners", "update", "predict", "n_predicted"), 0.0)

        def timed(fn, part):
            def wrapper(*a, **k):
                t0 = time.perf_counter()
                out = fn(*a, **k)
                dt = time.perf_counter() - t0
                clock["learners"] += dt
                clock[part] += dt
                if part == "predict":  # the rows predicted: the last argument
                    clock["n_predicted"] += len(a[-1])
                return out
            return wrapper

        bank.predict_affine = timed(bank.predict_affine, "predict")
        if hasattr(bank, "predict_projected"):  # the shared learner's path
            bank.predict_projected = timed(bank.predict_projected, "predict")
        bank.update = timed(bank.update, "update")
        self.fit_cpu = np.nan
        fit = ctrl.fit

        def timed_fit(*a, **k):
            t0 = time.process_time()
            out = fit(*a, **k)
            self.fit_cpu = time.process_time() - t0
            return out

        ctrl.fit = timed_fit
        filt, observe = ctrl.filter, ctrl.observe
        self.out: dict[str, list] = {"step": [], "filter": [], "learners": [], "update": [],
                                     "predict": [], "n_predicted": [], "n_active": [],
                                     "env_step": []}
        current = {"t": 0.0}

        def timed_filter(*a, **k):
            t0 = time.perf_counter()
            res = filt(*a, **k)
            current["t"] = time.perf_counter() - t0
            current["n"] = res.n_active
            return res

        def timed_observe(*a, **k):
            if ctrl.warming_up:
                clock.update(dict.fromkeys(clock, 0.0))
            t0 = time.perf_counter()
            z = observe(*a, **k)
            if not ctrl.warming_up and current.get("post", False):
                self.out["step"].append(current["t"] + time.perf_counter() - t0)
                self.out["filter"].append(current["t"])
                for part in ("learners", "update", "predict", "n_predicted"):
                    self.out[part].append(clock[part])
                self.out["n_active"].append(current["n"])
            current["post"] = not ctrl.warming_up
            clock.update(dict.fromkeys(clock, 0.0))
            return z

        ctrl.filter, ctrl.observe = timed_filter, timed_observe
        self.policy = NominalController(env)
        self.obs, _ = env.reset(seed=seed)
        self.remaining = env.unwrapped.warmup_steps + steps

    def step(self) -> None:
        """One control step (a reset when the episode ends); nothing once the prefix is done."""
        if self.remaining <= 0:
            return
        self.remaining -= 1
        action = self.policy(self.obs)
        timed = len(self.out["step"])
        t0 = time.perf_counter()
        self.obs, _, term, trunc, _ = self.env.step(action)
        if len(self.out["step"]) > timed:  # a timed control step: the wrapped env.step too
            self.out["env_step"].append(time.perf_counter() - t0)
        if term or trunc:
            self.obs, _ = self.env.reset()

    def result(self) -> dict[str, np.ndarray]:
        """Per-step times (s) of the step, the filter and the learners, barriers in the
        program, the fit's CPU time, K."""
        res = {k: np.asarray(v, dtype=float) for k, v in self.out.items()}
        res["fit_cpu_s"] = np.array([self.fit_cpu])
        res["n_barriers"] = np.array([self.env.unwrapped.n_barriers])
        self.env.close()
        return res


def time_config(spec: dict[str, Any], learner: str = "afvsgp", steps: int = 1500,
                seed: int = 0) -> dict[str, np.ndarray]:
    """Per-step times (s) of one filtered episode prefix (see the module docstring)."""
    ep = TimedEpisode(spec, learner, steps, seed)
    while ep.remaining > 0:
        ep.step()
    return ep.result()


def time_lockstep(specs: dict[str, dict[str, Any]], learner: str = "afvsgp",
                  steps: int = 1500, seed: int = 0, env_id: str = ENV_ID
                  ) -> dict[str, dict[str, np.ndarray]]:
    """:func:`time_config` of every configuration of ``specs`` with their episodes advanced
    one control step each in turn (the order reversed every step), so that a drift of the
    machine's speed hits them alike: their ratios are measured on the same seconds."""
    eps = {name: TimedEpisode(spec, learner, steps, seed, env_id)
           for name, spec in specs.items()}
    order = list(eps.values())
    while any(ep.remaining > 0 for ep in order):
        for ep in order:
            ep.step()
        order.reverse()
    return {name: ep.result() for name, ep in eps.items()}


def run(quick: bool = False, steps: int | None = None, rounds: int = 2,
        seeds: tuple[int, ...] = (0,), sequential: bool = False) -> dict[str, float]:
    """Median and p99 (s) of the step and learner times per configuration (pooled over the
    rounds and the episodes ``seeds``), fit time, and the ratios the issue asks for: K = 21
    against K = 1 for the learners' per-step cost. The configurations of a seed run in
    lockstep (:func:`time_lockstep`), or with ``sequential`` one after another (each then
    has the caches to itself, but a drift of the machine between them moves the ratios)."""
    steps = steps or (300 if quick else 1500)
    rounds = 1 if quick else rounds
    acc: dict[str, dict[str, list]] = {}
    for _ in range(rounds):
        for seed in seeds:
            if sequential:
                res = {name: time_config(spec, steps=steps, seed=seed)
                       for name, spec in CONFIGS.items()}
            else:
                res = time_lockstep(CONFIGS, steps=steps, seed=seed)
            for name, r in res.items():
                d = acc.setdefault(name, {})
                for k, v in r.items():
                    d.setdefault(k, []).append(v)
    out: dict[str, float] = {}
    for name, d in acc.items():
        step = np.concatenate(d["step"])
        learn = np.concatenate(d["learners"])
        out[f"{name}: step median_s"] = float(np.median(step))
        out[f"{name}: step p99_s"] = float(np.percentile(step, 99))
        env_step = np.concatenate(d["env_step"])
        out[f"{name}: env.step median_s"] = float(np.median(env_step))
        out[f"{name}: env.step p99_s"] = float(np.percentile(env_step, 99))
        filt = np.concatenate(d["filter"])
        out[f"{name}: filter median_s"] = float(np.median(filt))
        out[f"{name}: filter p99_s"] = float(np.percentile(filt, 99))
        out[f"{name}: learners median_s"] = float(np.median(learn))
        out[f"{name}: learners p99_s"] = float(np.percentile(learn, 99))
        out[f"{name}: update median_s"] = float(np.median(np.concatenate(d["update"])))
        n_pred = np.concatenate(d["n_predicted"])
        out[f"{name}: prediction per barrier_s"] = float(
            np.concatenate(d["predict"]).sum() / max(n_pred.sum(), 1.0))
        out[f"{name}: barriers in program (mean)"] = float(np.mean(np.concatenate(d["n_active"])))
        out[f"{name}: fit cpu_s"] = float(np.median(np.concatenate(d["fit_cpu_s"])))
    one = "1 (ee), arm settings"  # K = 21 against K = 1 at equal learner settings
    arm = "21 (arm), before the limits"  # the obstacle pairs alone, as the one sphere's
    out["learners median, K=21 / K=1"] = (out[f"{arm}: learners median_s"]
                                          / out[f"{one}: learners median_s"])
    for part in ("update median", "prediction per barrier"):  # the two parts of it
        out[f"{part}, K=21 / K=1"] = (out[f"{arm}: {part}_s"] / out[f"{one}: {part}_s"])
    out["fit, K=21 / K=1"] = out[f"{arm}: fit cpu_s"] / out[f"{one}: fit cpu_s"]
    for what in ("step", "env.step"):  # the 28 joint-limit barriers' price
        for q in ("median", "p99"):
            out[f"{what} {q}: with the 28 limits / before"] = (
                out[f"21 (arm): {what} {q}_s"] / out[f"{arm}: {what} {q}_s"])
    for q in ("median", "p99"):
        out[f"step {q}, K=21: arm / method settings"] = (
            out[f"21 (arm): step {q}_s"] / out[f"21 (arm), method settings: step {q}_s"])
    out["step median, K=21: clarabel only / with fast path"] = (
        out["21 (arm), clarabel only: step median_s"] / out["21 (arm): step median_s"])
    for q in ("median", "p99"):
        for what in ("solver", "learners", "only"):
            out[f"step {q}, K=21: numpy {what} / compiled"] = (
                out[f"21 (arm), numpy {what}: step {q}_s"] / out[f"21 (arm): step {q}_s"])
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="300 steps, one round")
    p.add_argument("--steps", type=int, default=None, help="timed steps per episode")
    p.add_argument("--rounds", type=int, default=2, help="interleaved rounds")
    p.add_argument("--seeds", type=int, nargs="+", default=[0],
                   help="episode seeds, pooled (default: 0)")
    p.add_argument("--sequential", action="store_true",
                   help="run the configurations one after another, not in lockstep")
    args = p.parse_args(argv)
    print(machine())
    print(calibration_line(), flush=True)
    out = run(args.quick, args.steps, args.rounds, tuple(args.seeds), args.sequential)
    for k, v in out.items():
        unit = " us" if k.endswith("_s") and "fit" not in k else ""
        val = v * 1e6 if unit else v
        print(f"{k:48s} {val:10.1f}{unit}" if unit else f"{k:48s} {val:10.3f}")


if __name__ == "__main__":
    main()
