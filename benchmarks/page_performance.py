"""Write docs/performance.md from the filter's timing runs.

    python benchmarks/page_performance.py            # writes docs/performance.md
    python benchmarks/page_performance.py --check    # exit 1 if it is not what this writes

Reads ``benchmarks/results/arm.json`` (the whole-arm step: the printed output of several runs
of ``python -m afvsgp_gym.benchmarks.arm`` in one sitting on one machine, each with its mode),
``benchmarks/results/solver.json`` (one run of ``python -m afvsgp_gym.benchmarks.solver``) and
``benchmarks/results/scale.json`` (one run each of ``python -m afvsgp_gym.benchmarks.scale`` and
``python benchmarks/oscbf_side_by_side.py --oscbf PATH``, one after the other); each file gives
its ``machine``, ``date``, ``code`` and the command. To refresh one, run the
command as the file says, put each printed output in ``runs`` (or ``output``) with the date
and the code version, and run this script.
"""

from __future__ import annotations

import re

from docgen import DOCS, RESULTS, main, measured, parse_output, provenance, read_json, table

ARM = RESULTS / "arm.json"
SOLVER = RESULTS / "solver.json"
SCALE = RESULTS / "scale.json"
PAGE = DOCS / "performance.md"

CONFIGS = {
    "1 (ee)": "1: the end-effector sphere (the method's M = 40, P = 1000)",
    "1 (ee), arm settings": "1: the end-effector sphere at the whole-arm settings",
    "7 (hand)": "7: the hand's spheres",
    "21 (arm)": "**21 + 28: the whole arm and the joint limits (default)**",
    "21 (arm), before the limits": "21: the whole arm before the joint limits",
    "21 (arm), method settings": "21, at the method's M = 40, P = 1000",
    "21 (arm), clarabel only": "21, every cone program to clarabel (no fast path)",
    "21 (arm), numpy solver": "21, cone program without its compiled path",
    "21 (arm), numpy learners": "21, learners without their compiled core",
    "21 (arm), numpy only": "21, no compiled code (as installed without a C compiler)",
    "42 (arm, 2 obstacles)": "42: the whole arm, two obstacles",
}


def span(values: list[float], fmt: str = "{:.0f}") -> str:
    lo, hi = fmt.format(min(values)), fmt.format(max(values))
    return lo if lo == hi else f"{lo}-{hi}"


def arm_section() -> list[str]:
    data = read_json(ARM)
    runs = [(r["mode"], parse_output(r["output"])) for r in data["runs"]]
    modes = list(dict.fromkeys(mode for mode, _ in runs))
    calib = sorted({m.group(0) for r in data["runs"]
                    for m in [re.search(r"^calibration: .*$", r["output"], re.M)] if m})
    out = ["## The filtered step", "",
           "Time per control step after the warm-up of the filter's own work "
           "(`SafetyController.filter` + `observe`: the barrier constraints, the learners' "
           "predictions for the barriers in the cone program, the cone program, the eq. 48 "
           "measurement and every learner's update) on the static Franka scenario, nominal "
           "model \"zero\", AFVSGP, seeds 0-2 pooled, one core, one BLAS thread. `learners`: "
           "the part spent in the learners (predictions and updates); `barriers in program`: "
           "the mean number of barriers near enough to the obstacle to enter the cone program; "
           "`env.step`: the whole wrapped step a user calls (physics, the env's barrier "
           "terms, the filter and the learning). The rows of 1, 7 and 42 barriers and the arm "
           "before the limits protect the obstacle pairs only; the other rows of 21 add the "
           "28 joint-limit barriers, as the default does.",
           "",
           measured(data),
           "",
           f"```bash\nOPENBLAS_NUM_THREADS=1 taskset -c 0 {data['benchmark']}\n```", ""]
    for mode in modes:
        vals = [v for m, v in runs if m == mode]
        rows = []
        for key, name in CONFIGS.items():
            if f"{key}: step median_s" not in vals[0]:
                continue

            def get(field: str, key: str = key, vals: list = vals) -> list[float]:
                return [v[f"{key}: {field}"] for v in vals]

            env_step = (span(get("env.step median_s"))
                        if f"{key}: env.step median_s" in vals[0] else "-")
            rows.append((name, span(get("step median_s")), span(get("step p99_s")),
                         span(get("learners median_s")), span(get("update median_s")),
                         span(get("prediction per barrier_s"), "{:.1f}"),
                         span(get("barriers in program (mean)"), "{:.2f}"), env_step))
        how = ("configurations one after another, as a robot loop runs one filter"
               if mode == "sequential" else
               "configurations advancing one step each in turn, so that their ratios are "
               "measured on the same seconds")
        out += [f"**{mode.capitalize()}** ({len(vals)} runs; {how}), microseconds, the range "
                "over the runs:", "",
                table(("barriers", "step median", "step p99", "learners median",
                       "update median", "prediction per barrier", "barriers in program",
                       "env.step median"), rows), ""]
    ratio_keys = [k for k in runs[0][1] if "/" in k]
    rows = [(k.replace(", K=21 / K=1", ", 21 learners / 1").replace(", K=21:", " at 21 barriers:"),
             *(span([v[k] for m, v in runs if m == mode], "{:.2f}") + "x" for mode in modes))
            for k in ratio_keys]
    out += ["Ratios within each run (range over the runs):", "",
            table(("ratio", *modes), rows), ""]
    if calib:
        parts = [dict(re.findall(r"([a-z0-9 /]+?) ([0-9.]+)(?:,|$)", c.removeprefix(
            "calibration: "))) for c in calib]
        cells = [f"{name.strip()} {span([float(p[name]) for p in parts], '{:.1f}')}"
                 for name in parts[0]]
        out += ["Calibration of the machine (the three costs a step is made of, to set "
                "machines side by side; range over the runs): " + ", ".join(cells) + ".", ""]
    return out


def solver_section() -> list[str]:
    data = read_json(SOLVER)
    v = parse_output(data["output"])
    ks = sorted({int(m.group(1)) for k in v if (m := re.match(r"K(\d+)_", k))})
    rows = []
    for k in ks:
        def cell(key: str, k: int = k) -> str:
            x = v.get(f"K{k}_{key}")
            return "-" if x is None else f"{x:.1f}"

        over = v.get(f"K{k}_socp_overhead_filter")
        rows.append((k, cell("qp_ours_with_backup_median_s"), cell("qp_ours_median_s"),
                     cell("qp_cbfpy_elastiqp_soft_median_s"),
                     "-" if over is None else f"{over:.2f}x"))
    return ["## The cone program alone", "",
            "`SOCPFilter.solve` on the same states as cbfpy's best configuration (elastiqp, "
            "soft constraints) for a known model (a QP), median microseconds per call over all "
            "calls; and the learned filter's cone program (SOCP) against clarabel's own solve "
            "time of the whole program on the feasible active calls. \"with backup\" is how "
            "the wrapper runs it: an infeasible program returns the backup action right after "
            "its infeasibility certificate; without one the certified max-worst-margin action "
            "is computed, which cbfpy does not do.", "",
            measured(data), "",
            f"```bash\nOPENBLAS_NUM_THREADS=1 taskset -c 0 {data['benchmark']}\n```", "",
            table(("barriers", "ours, QP, with backup", "ours, QP, no backup",
                   "cbfpy elastiqp", "SOCP: ours / clarabel's own solve"), rows), ""]


def _us(x: float) -> str:
    return f"{x:.0f}"


def scale_section() -> list[str]:
    data = read_json(SCALE)
    outputs = {r["command"]: parse_output(r["output"]) for r in data["runs"]}
    sc = outputs["python -m afvsgp_gym.benchmarks.scale"]
    osc = outputs["python benchmarks/oscbf_side_by_side.py --oscbf PATH"]
    versions = "; ".join(f"`{r['command']}`: {r['versions']}" for r in data["runs"])
    learners = (("per-pair learners", "per-pair (`afvsgp`, the default with this prior)"),
                ("shared learner", "shared (`afvsgp-shared`)"))
    rows = []
    for pairs in ("21", "525"):
        for key, name in learners:
            k = f"{pairs} pairs + 28 limits, {key}"
            rows.append((f"{pairs} + 28", name, _us(sc[f"{k}: step median_s"]),
                         _us(sc[f"{k}: step p99_s"]), _us(sc[f"{k}: update median_s"]),
                         _us(sc[f"{k}: env_step median_s"]), _us(sc[f"{k}: env_step p99_s"]),
                         f"{sc[f'{k}: barriers in program (mean)']:.1f}"))
    growth = {key: sc[f"525 pairs + 28 limits, {key}: env_step median_s"]
              / sc[f"21 pairs + 28 limits, {key}: env_step median_s"] for key, _ in learners}
    ours = ("ours, model known (oracle)", "ours, shared learner", "ours, per-pair learners")
    names = {ours[0]: "ours, model known (`oracle`)", ours[1]: "ours, shared learner",
             ours[2]: "ours, per-pair learners (the default with this prior)"}
    rows2 = []
    for k in ours:
        rows2.append((names[k], _us(osc[f"{k}: filter + learning median_s"]),
                      _us(osc[f"{k}: filter + learning p99_s"]),
                      _us(osc[f"{k}: OSCBF at its states median_s"]),
                      _us(osc[f"{k}: OSCBF at its states p99_s"]),
                      f"{osc[f'{k}: filter + learning median / OSCBF' + chr(39) + 's']:.2f}x",
                      f"{osc[f'{k}: barriers in program (mean)']:.1f}",
                      _us(osc[f"{k}: env.step median_s"]),
                      f"{osc[f'{k}: steps with cost']:.0f}"))
    rows2.append(("OSCBF at its speed test's random states", "-", "-",
                  _us(osc["OSCBF at its test's random states: median_s"]),
                  _us(osc["OSCBF at its test's random states: p99_s"]), "-", "-", "-", "-"))
    shared, per = (osc[f"{k}: filter + learning median / OSCBF's"] for k in ours[1:])
    return ["## Hundreds of barriers, and beside OSCBF", "",
            "Each obstacle pair has a learner of its own by default, so the learning grows "
            "with the number of obstacles; the shared learner learns the seven "
            "joint-acceleration errors once and projects them onto every pair "
            "([Learners](learners.md#the-shared-learner)), which needs the kinematics: both "
            "run with the nominal model \"kinematic\" (nothing of the dynamics known). "
            "`python -m afvsgp_gym.benchmarks.scale`: the static scenario's tracker with its "
            "obstacle alone (21 arm spheres x 1) and with 24 more spheres around the "
            "workspace (x 25), the four configurations in lockstep; microseconds per control "
            "step after the warm-up, `step` the filter and the learning, `env.step` the whole "
            "wrapped step.", "",
            measured(data), "", f"Versions: {versions}.", "",
            "```bash\nOPENBLAS_NUM_THREADS=1 taskset -c 0 python -m afvsgp_gym.benchmarks.scale"
            "\n```", "",
            table(("barriers", "learner", "step median", "step p99", "update median",
                   "env.step median", "env.step p99", "barriers in program"), rows), "",
            "The wrapped step at 525 pairs against 21: "
            + ", ".join(f"{name.split(' (')[0]} {growth[key]:.2f}x" for key, name in learners)
            + ".", "",
            "[OSCBF](https://github.com/StanfordASL/oscbf) (Morton and Pavone, IROS 2025), a "
            "whole-body "
            "torque CBF filter in jax with the model known, on its own cluttered-tabletop "
            "scene: 25 spheres and a table against 21 arm spheres, "
            f"{osc['OSCBF: constraints']:.0f} constraints (ours add the 28 joint-limit "
            "barriers). `python benchmarks/oscbf_side_by_side.py` (its docstring says how to "
            "install a copy of OSCBF beside this package) runs each configuration of ours (the "
            "learned ones with the nominal model \"kinematic\", as above) in "
            "lockstep with OSCBF's compiled controller (its operational-space nominal torque "
            "and its QP) called at the state our episode is in, toward the same reference; "
            "`/ OSCBF` is the ratio of the two medians in that lockstep. Our step is the "
            "filter and the learning (the tracker's torque is not in it; OSCBF's nominal "
            "controller is in its step). Interleaved with jax's calls our step is slower than "
            "the same episode alone, so the ratios are on the conservative side.", "",
            "```bash\nOPENBLAS_NUM_THREADS=1 taskset -c 0 python benchmarks/oscbf_side_by_side.py "
            "--oscbf PATH\n```", "",
            table(("filter", "ours: median", "ours: p99", "OSCBF: median", "OSCBF: p99",
                   "ours / OSCBF", "barriers in program", "our env.step median",
                   "steps with cost"), rows2), "",
            f"With the shared learner our learned filter takes {shared:.2f}x OSCBF's "
            f"known-model step at the same states; with the per-pair learners {per:.2f}x.",
            ""] + crossover_part(outputs) + defaults_part(outputs)


def defaults_part(outputs: dict[str, dict[str, float]]) -> list[str]:
    """``SafetyFilter``'s default learner at 21 and 525 pairs (``--defaults``), if it ran."""
    d = outputs.get("python -m afvsgp_gym.benchmarks.scale --defaults")
    if not d:
        return []
    rows = []
    for pairs in (21, 525):
        k = f"default, {pairs} pairs + 28 limits"
        rows.append((f"{pairs} + 28", "shared" if d[f"{k}: shared learner"] else "per-pair",
                     _us(d[f"{k}: step median_s"]), _us(d[f"{k}: step p99_s"]),
                     _us(d[f"{k}: env_step median_s"]), _us(d[f"{k}: env_step p99_s"])))
    return ["With `SafetyFilter`'s defaults and the robot's own model as the prior (the "
            "scale benchmark's two scenes in lockstep), the wrapped step at 525 pairs costs "
            f"{d['default: env_step median, 525 / 21 pairs']:.2f}x the step at 21, and the "
            "filter and the learning "
            f"{d['default: step median, 525 / 21 pairs']:.2f}x:", "",
            "```bash\nOPENBLAS_NUM_THREADS=1 taskset -c 0 python -m afvsgp_gym.benchmarks.scale "
            "--defaults\n```", "",
            table(("barriers", "learner the default took", "step median", "step p99",
                   "env.step median", "env.step p99"), rows), ""]


def crossover_part(outputs: dict[str, dict[str, float]]) -> list[str]:
    """Where the shared learner's step becomes the faster (``--crossover``), if it ran."""
    cross = outputs.get("python -m afvsgp_gym.benchmarks.scale --crossover")
    if not cross:
        return []
    counts = sorted({int(m.group(1)) for k in cross
                     if (m := re.match(r"(\d+) pairs, ", k))})
    rows = [(n, _us(cross[f"{n} pairs, per-pair: step median_s"]),
             _us(cross[f"{n} pairs, shared: step median_s"]),
             f"{cross[f'{n} pairs: step median, shared / per-pair']:.2f}x") for n in counts]
    ratio = {n: cross[f"{n} pairs: step median, shared / per-pair"] for n in counts}
    faster = [n for n in counts if ratio[n] < 0.95]
    even = [str(n) for n in counts if 0.95 <= ratio[n] <= 1.05]
    first = (("the two are within 5 % at " + ", ".join(even) + " pairs; " if even else "")
             + (f"the shared learner is the faster from {faster[0]} pairs on" if faster
                else "the shared learner is not the faster at any of these counts"))
    return ["**The default.** `SafetyFilter`'s default learner (`\"auto\"`) is the shared "
            "one where the prior knows the dynamics and the pairs are many "
            "([Learners](learners.md#the-shared-learner)): with the robot's own model as the "
            "prior it was as safe and tracked as well; with nothing of the dynamics known it "
            "tracked worse ([Safety](safety.md#the-shared-learner)). Where its step becomes "
            "the faster, the static scenario's tracker with the first obstacles of the "
            "clutter above and the robot's own model as the prior, each count's two learners "
            f"in lockstep: {first} (the default takes it above "
            "`FrankaObstacleEnv.SHARED_LEARNER_PAIRS` sphere pairs).", "",
            "```bash\nOPENBLAS_NUM_THREADS=1 taskset -c 0 python -m afvsgp_gym.benchmarks.scale "
            "--crossover\n```", "",
            table(("pairs", "per-pair: step median", "shared: step median", "shared / per-pair"),
                  rows), ""]


def build() -> dict:
    out = [provenance("benchmarks/page_performance.py",
                      ["benchmarks/results/arm.json", "benchmarks/results/solver.json",
                       "benchmarks/results/scale.json"]), "",
           "# Performance", "",
           "What one filtered control step costs, and the cone program against another CBF "
           "library. Absolute times are the machine's; the ratios within one run carry over "
           "better. Run control loops with one BLAS thread (`OPENBLAS_NUM_THREADS=1`): with a "
           "thread pool and the other core busy the step's tail grows by an order of "
           "magnitude.", ""]
    out += arm_section()
    out += solver_section()
    out += scale_section()
    out += ["## Other benchmarks", "",
            "`afvsgp-gym bench [--quick] [--only gp,envs,filter,sweep]` prints the speed figures "
            "of the learners (one AFVSGP step at the paper's size against VSGP and SOGP), the "
            "environments (steps per second with the barrier terms, against Gymnasium's "
            "Ant-v5 in the same rounds), the filter and the sweep executors (episodes per "
            "minute with one and two worker processes, and Ray's overhead with the `cluster` "
            "extra), all measured in one run.", "",
            "`python benchmarks/step_anatomy.py` splits the whole-arm step by the number of "
            "barriers in the cone program and by the solver's path; "
            "`python benchmarks/bit_identity.py` hashes four filtered episodes, to check that "
            "a change keeps the arithmetic bit for bit on one machine.", ""]
    return {PAGE: "\n".join(out)}


if __name__ == "__main__":
    raise SystemExit(main(__doc__, build))
