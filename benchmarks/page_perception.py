"""Write docs/perception.md from the perception sweep's records.

    python benchmarks/page_perception.py            # writes docs/perception.md
    python benchmarks/page_perception.py --check    # exit 1 if it is not what this writes

Reads ``benchmarks/results/perception.jsonl.gz``: the records of ``afvsgp-gym sweep
benchmarks/configs/perception.toml`` (all of it or a slice of its seeds; the page says how many
episodes each row has), each with its ``code_version``, ``machine`` and ``date``.
"""

from __future__ import annotations

from acceptance_tables import SCENARIOS, prior, scenario, summary
from docgen import (
    DOCS,
    RESULTS,
    hold_memory_caveat,
    main,
    measured,
    provenance,
    read_json,
    read_jsonl,
    table,
)
from page_adversarial import cost_cell, meta

SOURCE = RESULTS / "perception.jsonl.gz"
CONSISTENCY = RESULTS / "estimator_consistency.json"
ENCODERS = RESULTS / "encoder_noise.json"
PAGE = DOCS / "perception.md"
CAMERAS = ("1cm_60Hz_30ms", "1cm_30Hz_60ms", "2cm_30Hz_100ms", "2cm_250Hz_0ms")
FILTERS = {"kalman": "AFVSGP, Kalman estimate (the default)",
           "raw": "AFVSGP, raw reading as the truth",
           "oracle": "oracle (exact model), Kalman estimate"}
REPRODUCE = """\
afvsgp-gym sweep benchmarks/configs/perception.toml --out perception.jsonl --workers 2
gzip -c perception.jsonl > benchmarks/results/perception.jsonl.gz
python benchmarks/page_perception.py"""


def camera(rec: dict) -> str:
    kw = rec["config"]["env_kwargs"]
    noise = round(100 * kw.get("obstacle_noise", 0.0))
    return (f"{noise}cm_{kw.get('obstacle_rate', 250):g}Hz_"
            f"{round(1000 * kw.get('obstacle_delay', 0.0))}ms")


def pushed(rec: dict) -> bool:
    return rec["config"]["env_kwargs"].get("push") is not None


def kind(rec: dict) -> str:
    return rec["block"].split("_", 1)[0]


def camera_label(name: str) -> str:
    noise, rate, delay = name.split("_")
    return (f"{noise.removesuffix('cm')} cm, {rate.removesuffix('Hz')} Hz, "
            f"{delay.removesuffix('ms')} ms")


def rows_by_setting(recs: list[dict]) -> list[tuple]:
    rows = []
    for cam in CAMERAS:
        for push in (False, True):
            cell = [r for r in recs if camera(r) == cam and pushed(r) == push]
            if not cell:
                continue
            by = {k: [r for r in cell if kind(r) == k] for k in FILTERS}
            row = [camera_label(cam), "on" if push else "off"]
            for k in FILTERS:
                group = by[k]
                if not group:
                    row += ["-", "-"]
                    continue
                s = summary(group)
                row += [f"{s['cost']} / {s['n']}", f"{100 * s['min_h']:.1f}"]
            oracle = by["oracle"]
            if by["kalman"] and oracle:
                row.append(f"{summary(by['kalman'])['track'] / summary(oracle)['track']:.2f}")
            else:
                row.append("-")
            rows.append(tuple(row))
    return rows


def rows_by_prior(recs: list[dict]) -> list[tuple]:
    rows = []
    for k in FILTERS:
        for pr in ("zero", "perturbed"):
            for sc in SCENARIOS:
                group = [r for r in recs if kind(r) == k and scenario(r) == sc
                         and r["config"]["env_kwargs"].get("nominal_model") == pr]
                if not group:
                    continue
                s = summary(group)
                rows.append((FILTERS[k], pr, sc, s["n"], cost_cell(s),
                             f"{100 * s['bound']:.3g} %", f"{100 * s['min_h']:.1f}",
                             f"{s['track']:.4f} ({s['track_se']:.4f})", f"{s['backup']:.0f}"))
    return rows


def consistency(res: dict) -> list[str]:
    rows = [(f"{r['process_std']:g}", f"{100 * r['noise']:g} cm, {r['rate']:g} Hz, "
             f"{1000 * r['delay']:g} ms",
             *(f"{r[k]['nees_per_dof']:.2f}" if k in r else "-" for k in ("moving", "still")),
             f"{100 * r.get('moving', r['still'])['velocity_std']:.1f}") for r in res["rows"]]
    return ["## The estimator's consistency", "",
            "The normalised estimation error squared of `[p, v]` per degree of freedom (1: "
            "consistent; above: overconfident) on the dynamic and random scenes' obstacles, "
            "6 seeds each, after the first second (`python benchmarks/estimator_consistency.py`"
            "): the default process noise is the smallest that is not overconfident while the "
            "obstacles move.", "",
            table(("process std", "camera", "NEES/dof moving", "NEES/dof still",
                   "velocity std [cm/s]"), rows), ""]


def encoders(res: dict) -> list[str]:
    rows = [(r["prior"], f"{r['velocity_noise']:g}", r["seed"], r["cost_steps"],
             f"{100 * r['min_h']:.1f}", r["backup_steps"], f"{r['tracking_error_mean']:.4f}",
             f"{r['pair_noise_std']:.3f}", f"{r['joint_noise_std']:.2f}",
             f"{r['difference_noise_std']:.2f}", f"{100 * r['miss_rate']:.2f} %")
            for r in res["rows"]]
    return ["## Noisy encoders", "",
            "AFVSGP behind the tracker on the static scene with `velocity_noise` (and a tenth "
            "of it as `position_noise`; `python benchmarks/encoder_noise.py`). The eq. 48 "
            "samples difference the measured joint speeds, whose noise alone is `sqrt(2) "
            "sigma_v / dt` on a joint's acceleration: the learners take it as their noise "
            "(no collapse, nothing non-finite), the band widens with it, and the program is "
            "infeasible more often, so the brake holds the arm and tracking suffers. The "
            "joint speeds are not filtered before the difference yet.", "",
            table(("prior", "velocity noise [rad/s]", "seed", "cost steps", "min h [cm]",
                   "backup", "tracking [m]", "pair noise std", "joint noise std",
                   "difference's std", "miss"), rows), ""]


def code_versions(recs: list[dict]) -> list[str]:
    """A paragraph on the Kalman rows' code versions when there are several (their seeds
    differ, and a later default changed how often the brake holds the arm)."""
    kalman = [r for r in recs if kind(r) == "kalman"]
    codes = list(dict.fromkeys(r["code_version"] for r in sorted(kalman, key=lambda r: r["seed"])))
    if len(codes) < 2:
        return []
    parts = []
    for code in codes:
        group = [r for r in kalman if r["code_version"] == code]
        seeds = sorted({r["seed"] for r in group})
        zero = summary([r for r in group if prior(r) == "zero"])
        parts.append(f"`{code}` seeds {seeds[0]}-{seeds[-1]} (prior \"zero\": tracking "
                     f"{zero['track']:.4f} m, backup {zero['backup']:.0f} steps per episode)")
    return ["The Kalman rows ran at several code versions on different seeds: "
            + "; ".join(parts) + ". From `2ab9b5a` the joint-speed barriers take the conformal "
            "multiplier ([Any policy](adversarial.md)): with nothing known it holds the arm "
            "more often and tracks worse, so the tracking columns mix the two.", ""]


def build() -> dict:
    out = [provenance("benchmarks/page_perception.py", ["benchmarks/results/perception.jsonl.gz"]),
           "", "# Perception and pushes", "",
           "The Franka envs can show the filter the world through sensors instead of the "
           "simulator's state (env options, all seeded by `reset(seed)`): a camera on the "
           "obstacles (`obstacle_noise` m of Gaussian noise per sample, `obstacle_rate` Hz, "
           "`obstacle_delay` s of latency; between samples the last one holds), encoders on the "
           "joints (`velocity_noise` rad/s, `position_noise` rad) and random pushes on the "
           "links (`push={\"force\": N, \"duration\": s, \"rate\": 1/s}`, through MuJoCo's "
           "`xfrc_applied`). The observation and every barrier term the filter receives (the "
           "oracle's too: it has the exact dynamics, not the exact perception) come from the "
           "sensed state; `info`'s `h`, `collision`, `cost` and `delta_b_true` from the true "
           "one, with `obstacle_error`, `joint_position_error`, `joint_velocity_error` and "
           "`push_active` beside them.", "",
           "`SafetyFilter` estimates the obstacles with a Kalman filter (constant velocity, "
           "process noise `estimator_process_std` = 0.03 m s^-1.5, the smallest that is "
           "consistent on the scenarios' obstacles; `obstacle_estimator=\"kalman-ca\"` for "
           "constant acceleration) that fuses each sample when it arrives "
           "and predicts over the delay to the current period. Its covariance goes to the "
           "barrier terms as the first-order covariance of each pair's `[h, h', lf]` "
           "(`afvsgp_gym.envs.perception.pair_covariance`, with `lf`'s second-order mean "
           "error, the curvature's `2 sigma_v^2 / |d|`, taken out), and the controller backs "
           "each constraint off by `beta` standard deviations of it "
           "(`SafetyController.sensing_std`): the chance constraint on the sensing error, "
           "added to the learned band's (the two standard deviations add, which is "
           "conservative). The eq. 48 sample is taken with the estimate predicted without "
           "the newest sample, so the learners see the arm's model error, not the jump of a "
           "measurement update. `obstacle_estimator=\"raw\"` is the baseline: the camera's "
           "reading (the newest sample, the difference of the last two, zero acceleration) "
           "taken as the truth.", "",
           "**Pushes.** A push `F` at a point `p` of a link adds the joint torques `J_p' F`, so "
           "each barrier's `h''` is off by `n' J_s M^-1 J_p' F` while it lasts, which no filter "
           "that does not measure the force can see beforehand. What holds is input-to-state "
           "safety (Kolathaya and Ames 2019): with a bounded error `delta` in `h''` the linear "
           "HOCBF chain keeps `h >= -delta / (a_1 a_2)` at worst, and a push that lasts `T` "
           "moves a sphere at most about `delta T^2 / 2` before the filter brakes the speed it "
           "left (a 10 N, 0.1 s push on a few kilograms of effective mass: a few centimetres), "
           "inside the 15 cm activation distance and the braking margin. The learners do not "
           "absorb a push (it is over before a window of samples sees it); it reaches them as a "
           "few outlying eq. 48 samples. The grid measures it.", ""]
    if CONSISTENCY.exists():
        out += consistency(read_json(CONSISTENCY))
    if ENCODERS.exists():
        out += encoders(read_json(ENCODERS))
    if not SOURCE.exists():
        out += ["No results yet: run", "", "```bash", REPRODUCE, "```"]
        return {PAGE: "\n".join(out) + "\n"}
    recs = read_jsonl(SOURCE)
    seeds = {k: sorted({r["seed"] for r in recs if kind(r) == k}) for k in FILTERS}
    full = {"kalman": 21, "raw": 5, "oracle": 5}
    covered = "; ".join(f"{k} {len(v)} of {full[k]} seeds" for k, v in seeds.items() if v)
    out += ["## The grid", "", measured(meta(recs)) + f" {len(recs)} episodes of "
            f"`benchmarks/configs/perception.toml` ({covered}) behind the nominal tracker, "
            "cost counted from the true state.", "",
            *code_versions(recs), *hold_memory_caveat(recs),
            "## By camera and pushes", "",
            "Episodes with cost and the smallest true `h` (cm) of each filter over the three "
            "scenarios (and for AFVSGP the priors \"zero\" and \"perturbed\"); the last column "
            "is AFVSGP's tracking error over the oracle's on the same settings.", "",
            table(("camera (noise, rate, delay)", "pushes",
                   "Kalman: cost", "min h", "raw: cost", "min h", "oracle: cost", "min h",
                   "tracking / oracle"), rows_by_setting(recs)), "",
            "## By filter, prior and scenario", "",
            table(("filter", "prior", "scenario", "episodes", "with cost", "95 % bound",
                   "min h [cm]", "tracking [m] (s.e.)", "backup"), rows_by_prior(recs)), "",
            "To regenerate:", "", "```bash", REPRODUCE, "```"]
    return {PAGE: "\n".join(out).rstrip("\n") + "\n"}


if __name__ == "__main__":
    raise SystemExit(main(__doc__, build))
