"""The measured runs of the Franka bridge on its MuJoCo stand-in, behind docs/robot.md.

    python benchmarks/robot_runs.py                  # every run (about 15 minutes)
    python benchmarks/robot_runs.py --only 60s-fifo  # one run again (``--list``: the labels)
    python benchmarks/page_robot.py                  # then the page

Appends one JSON object per run to ``benchmarks/results/robot.jsonl``: the run's
:class:`~afvsgp_gym.robots.bridge.BridgeReport` (``afvsgp-gym robot --json``'s counters;
``seconds`` is the time it took, ``requested_seconds`` the run's length), its ``label``,
``kind``, settings, ``scheduler``, ``machine``, ``kernel``, ``date`` (UTC day), ``code``
(the short hash of HEAD, ``-dirty`` when the package differs from it) and the
``load_average`` at its end. The page reads the last record of each label.

Two kinds of run, with the default agent (``nominal``), learner (``none``) and the stand-in's
1 kg payload its model does not know unless the run says otherwise:

- ``wall-clock``: what ``afvsgp-gym robot --simulate`` runs (``run_simulated``), paced at
  1 kHz by the wall clock with the 0.9 ms budget, at ``SCHED_FIFO`` 50 (the command's
  default) or normal priority (``--rt-priority 0``). Its figures depend on the machine and on
  what else runs on it.
- ``stepped``: the stand-in one tick per call (``realtime=False``) and a budget of 1 s, so
  no step falls back: the safety figures depend only on the code (deterministic; the camera
  noise is seeded), the step times are still the wall clock's. ``min_true_h`` is the smallest
  true clearance (the stand-in's ``clearance``), ``min_h`` the measured one (from the
  obstacle estimate).

The ``adversarial-`` runs are stepped runs of the policies built to break the filter
(``ram``, ``swing1``-``swing7``, ``random``; seeds 0 and 1), with the self-collision barriers
(the bridge's default) and, ``-no-self-collision``, without them; ``cost_kinds`` counts the
ticks of each kind of cost.

The ``-numpy-arm`` runs repeat a stepped run with the bridge's sphere kinematics and pair
terms on their numpy path (``arm_backend``; the extension ``afvsgp_gym.robots._arm`` off, the
filter's extensions on): the same ticks, to time what the compiled ones save on the loop.

Run it with ``OPENBLAS_NUM_THREADS=1`` (the bridge's setting) and ``MUJOCO_GL=egl``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import platform
import subprocess
from pathlib import Path

from afvsgp_gym._compiled import resolve
from afvsgp_gym.benchmarks._machine import machine
from afvsgp_gym.robots.run import build_bridge, realtime_priority, run_simulated
from afvsgp_gym.robots.simulated import SimulatedFranka, Torques

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "robot.jsonl"

DEFAULT_BOUND = (3.0, 3.0, 3.0, 3.0, 1.0, 1.0, 1.0)
SMALL_BOUND = (2.0, 2.0, 2.0, 2.0, 0.5, 0.5, 0.5)
NO_BOUND = (0.0,) * 7
#: The bridge's policies built to break the filter (``afvsgp_gym.robots.policies``).
ADVERSARIAL = ("ram", *(f"swing{j}" for j in range(1, 8)), "random")

#: label -> settings. ``realtime``: wall-clock; ``rt_priority``: SCHED_FIFO priority or None;
#: ``payload_kg``: the stand-in's payload its model does not know (0: none, the model exact
#: but for the joint damping, which is what declaring the payload to a robot leaves).
RUNS: dict[str, dict] = {
    "10s-normal": dict(kind="wall-clock", seconds=10.0, rt_priority=None),
    "10s-fifo": dict(kind="wall-clock", seconds=10.0, rt_priority=50),
    "60s-fifo": dict(kind="wall-clock", seconds=60.0, rt_priority=50),
    "bound-default": dict(kind="stepped", seconds=16.0, torque_error_nm=DEFAULT_BOUND),
    "bound-small": dict(kind="stepped", seconds=16.0, torque_error_nm=SMALL_BOUND),
    "bound-none": dict(kind="stepped", seconds=16.0, torque_error_nm=NO_BOUND),
    "bound-none-no-payload": dict(kind="stepped", seconds=16.0, torque_error_nm=NO_BOUND,
                                  payload_kg=0.0),
    "perception-exact": dict(kind="stepped", seconds=14.0),
    "perception-noise-1cm": dict(kind="stepped", seconds=14.0, obstacle_noise_m=0.01),
    "learner-afvsgp": dict(kind="stepped", seconds=16.0, learner="afvsgp"),
    # the bridge's self-collision barriers (opt-in): the price of their step
    "10s-fifo-self-collision": dict(kind="wall-clock", seconds=10.0, rt_priority=50,
                                    self_collision=True),
    "bound-default-self-collision": dict(kind="stepped", seconds=16.0, self_collision=True),
    "60s-fifo-self-collision": dict(kind="wall-clock", seconds=60.0, rt_priority=50,
                                    self_collision=True),
    # the compiled sphere kinematics and pair terms against their numpy path (the extension
    # "arm" off, the filter's on): the same ticks, the step's time
    "bound-default-numpy-arm": dict(kind="stepped", seconds=16.0, arm_backend="numpy"),
    "bound-default-self-collision-numpy-arm": dict(kind="stepped", seconds=16.0,
                                                   self_collision=True, arm_backend="numpy"),
    # a learner at 1 kHz: its warm-up fit in a process of its own (the default on the loop)
    "10s-fifo-learner-afvsgp": dict(kind="wall-clock", seconds=10.0, rt_priority=50,
                                    learner="afvsgp"),
    # the policies built to break the filter, two seeds each, with the self-collision
    # barriers (the bridge's default) and without them
    **{f"adversarial-{agent}-{seed}{suffix}": dict(kind="stepped", seconds=16.0, agent=agent,
                                                    seed=seed, self_collision=on)
       for agent in ADVERSARIAL for seed in (0, 1)
       for suffix, on in (("", True), ("-no-self-collision", False))},
}
SETTINGS = dict(agent="nominal", learner="none", torque_error_nm=DEFAULT_BOUND,
                payload_kg=1.0, obstacle_noise_m=0.0, rt_priority=None, self_collision=False,
                arm_backend="auto", seed=0)


def filter_kwargs(s: dict) -> dict:
    """The bridge's ``filter_kwargs``: the default backend, or the default with the
    extension ``"arm"`` (the kinematics and terms) off; a stepped run with a learner seeds
    the warm-up's exploration noise (its figures then depend on the code only)."""
    out = {} if s["arm_backend"] == "auto" else {
        "backend": dataclasses.replace(resolve("auto"), arm=False)}
    if s["kind"] == "stepped" and s["learner"] != "none":
        out["seed"] = 0
    return out


def code_version() -> str:
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()

    try:
        head = git("rev-parse", "--short", "HEAD")
        dirty = git("status", "--porcelain", "--", "afvsgp_gym")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


def kernel() -> str:
    """The kernel's name and release, and whether it is a real-time (PREEMPT_RT) one."""
    rt = "PREEMPT_RT" if "PREEMPT_RT" in platform.version() else "not PREEMPT_RT"
    return f"{platform.system()} {platform.release()} ({rt})"


def stepped(s: dict) -> dict:
    """A run one tick per call with a budget no step reaches; the report, the smallest
    true clearance and the ticks of each kind of cost (``cost_kinds``: a sphere inside an
    obstacle, an arm geom touching one, a joint limit, the arm touching itself)."""
    robot = SimulatedFranka(realtime=False, payload_mass=s["payload_kg"],
                            obstacle_noise=s["obstacle_noise_m"])
    closest = [math.inf]
    kinds = dict(inside=0, contact=0, limit=0, self_contact=0)

    def cost() -> bool:  # SimulatedFranka.cost, its four checks counted apart
        h = float(robot.clearance().min())
        closest[0] = min(closest[0], h)
        d = robot.data
        hits = {"inside": h < 0.0, "contact": robot.contact(),
                "limit": robot.joint_limits.violation(d.qpos[:7], d.qvel[:7]),
                "self_contact": robot.self_contact()}
        for kind, hit in hits.items():
            kinds[kind] += int(bool(hit))
        return any(hits.values())

    bridge = build_bridge(robot, robot.load_model(), Torques, chain=robot.kinematics,
                          obstacle_radii=[o.radius for o in robot.obstacles],
                          obstacles=robot.obstacle_estimate, limits=robot.joint_limits,
                          agent=s["agent"], learner=s["learner"], spheres=robot.spheres,
                          budget=s["budget_ms"] * 1e-3, cost=cost,
                          torque_error=list(s["torque_error_nm"]),
                          self_collision=s["self_collision"], filter_kwargs=filter_kwargs(s),
                          background_fit=False,  # the fit in the loop: the same ticks each run
                          seed=s["seed"])
    report = bridge.run(s["seconds"])
    report.lost_commands = robot.lost_commands
    return {**report.to_dict(), "cost_kinds": kinds,
            "min_true_h": closest[0] if math.isfinite(closest[0]) else None}


def wall_clock(s: dict) -> dict:
    """What ``afvsgp-gym robot --simulate`` runs."""
    report = run_simulated(s["seconds"], agent=s["agent"], learner=s["learner"],
                           budget=s["budget_ms"] * 1e-3,
                           torque_error=list(s["torque_error_nm"]),
                           robot_kwargs={"payload_mass": s["payload_kg"],
                                         "obstacle_noise": s["obstacle_noise_m"]},
                           self_collision=s["self_collision"], filter_kwargs=filter_kwargs(s),
                           seed=s["seed"])
    return report.to_dict()


def run(label: str, code: str, host: str) -> dict:
    s = {**SETTINGS, **RUNS[label]}
    s["budget_ms"] = 0.9 if s["kind"] == "wall-clock" else 1000.0
    with realtime_priority(s["rt_priority"]) as scheduler:
        out = wall_clock(s) if s["kind"] == "wall-clock" else stepped(s)
    s["torque_error_nm"] = list(s["torque_error_nm"])
    s["requested_seconds"] = s.pop("seconds")  # ``seconds`` is the report's: as it ran
    day = datetime.datetime.now(datetime.timezone.utc).date().isoformat()
    return {"label": label, **s, "scheduler": scheduler, **out, "machine": host,
            "kernel": kernel(), "date": day, "code": code,
            "load_average": [round(v, 2) for v in os.getloadavg()]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", default=None, metavar="LABEL[,LABEL]",
                        help="run these labels only")
    parser.add_argument("--list", action="store_true", help="print the labels and exit")
    parser.add_argument("--out", type=Path, default=OUT, help=f"default {OUT.name}")
    args = parser.parse_args()
    if args.list:
        print("\n".join(f"{k}: {v}" for k, v in RUNS.items()))
        return
    labels = list(RUNS) if args.only is None else args.only.split(",")
    unknown = [lb for lb in labels if lb not in RUNS]
    if unknown:
        parser.error(f"unknown label(s) {', '.join(unknown)}; valid: {', '.join(RUNS)}")
    if os.environ.get("OPENBLAS_NUM_THREADS") != "1":
        print("warning: OPENBLAS_NUM_THREADS is not 1 (the bridge's setting)")
    code, host = code_version(), machine()
    for label in labels:
        rec = run(label, code, host)
        with open(args.out, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(rec) + "\n")
        st = rec["step_time_ms"]
        print(f"{label}: {rec['steps']} steps, {rec['deadline_misses']} misses, "
              f"{rec['cost_steps']} with cost, p50 {st.get('p50', math.nan):.3f} ms, "
              f"{rec['scheduler']}, stop: {rec['stop_reason']}")


if __name__ == "__main__":
    main()
