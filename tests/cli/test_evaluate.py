"""`afvsgp-gym evaluate` on the point mass: the report against a hand-counted loop."""

import csv
import json
import math

import gymnasium as gym
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401
from afvsgp_gym.agents import NominalController
from afvsgp_gym.cli import main
from afvsgp_gym.evaluation import EPISODE_FIELDS
from afvsgp_gym.wrappers import SafetyFilter

PM = "afvsgp_gym/PointMassObstacle-v0"
STEPS = 400


def _reference_clearance(base) -> float:
    """Independent of evaluation: clearance of the reference's agent sphere from the obstacles."""
    r = base.reference.state(base.time)[0]
    return min(np.linalg.norm(r - ob.state(base.time)[0]) - ob.radius - base.agent_radius
               for ob in base.obstacles)


def _hand_count(learner: str, seed: int) -> dict:
    env = SafetyFilter(gym.make(PM), learner=learner, seed=seed, backup=None)
    policy = NominalController(env)
    obs, _ = env.reset(seed=seed)
    base = env.unwrapped
    ret, hs, cost, coll, active, infeasible, track = 0.0, [], 0, 0, 0, 0, []
    for step in range(1, STEPS + 1):
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        ret += reward
        hs.append(info["h"])
        cost += info["cost"] > 0
        coll += bool(info["collision"])
        active += bool(info["filter_active"])
        infeasible += not info["filter_feasible"]
        if step > base.warmup_steps and info["reference_h"] >= 0.05:
            r = base.reference.state(base.time)[0]
            track.append(float(np.linalg.norm(base._p - r)))  # the plant's float64 state
        if terminated or truncated:
            break
    env.close()
    hs = np.array(hs)
    return {"steps": len(hs), "return": ret, "cost_steps": cost,
            "violation_steps": int((hs < 0).sum()), "min_h": float(hs.min()),
            "contact_steps": coll, "interventions": active, "infeasible_steps": infeasible,
            "tracking_error_mean": float(np.mean(track)), "tracking_error_max": max(track)}


def test_json_and_csv_match_a_hand_counted_loop(tmp_path, capsys):
    jpath, cpath = tmp_path / "out" / "report.json", tmp_path / "report.csv"
    rc = main(["evaluate", "--env", PM, "--agent", "nominal", "--compare", "none,oracle",
               "--episodes", "2", "--seed", "3", "--max-steps", str(STEPS), "--json", str(jpath),
               "--csv", str(cpath), "--no-progress", "--filter-kwargs", '{"backup": null}'])
    assert rc == 0
    out = capsys.readouterr().out
    assert "Episodes" in out and "Summary" in out
    data = json.loads(jpath.read_text())
    assert set(data) == {"episodes", "summary"}
    assert len(data["episodes"]) == 4
    for learner in ("none", "oracle"):
        expected = [_hand_count(learner, 3 + i) for i in range(2)]
        got = [r for r in data["episodes"] if r["learner"] == learner]
        for i, (e, g) in enumerate(zip(expected, got, strict=True)):
            assert g["episode"] == i and g["seed"] == 3 + i
            for key in ("steps", "cost_steps", "violation_steps", "contact_steps",
                        "interventions", "infeasible_steps"):
                assert g[key] == e[key], (learner, i, key)
            for key in ("return", "min_h", "tracking_error_mean", "tracking_error_max"):
                assert g[key] == pytest.approx(e[key], rel=1e-9), (learner, i, key)
            assert g["filter_time_median_s"] > 0 and g["filter_time_p99_s"] >= \
                g["filter_time_median_s"]
        s = data["summary"][learner]
        assert s["episodes"] == 2
        assert s["violation_steps"] == sum(e["violation_steps"] for e in expected)
        assert s["episodes_with_cost"] == sum(e["cost_steps"] > 0 for e in expected)
        assert s["episodes_with_violation"] == sum(e["violation_steps"] > 0 for e in expected)
        assert s["tracking_error_mean"] == pytest.approx(
            np.mean([e["tracking_error_mean"] for e in expected]))
        assert s["min_h"] == pytest.approx(min(e["min_h"] for e in expected))
        assert s["return_mean"] == pytest.approx(np.mean([e["return"] for e in expected]))
    # nominal-only filter with the zero model (and no brake backup) violates; the oracle not
    assert data["summary"]["none"]["violation_steps"] > 0
    assert data["summary"]["oracle"]["violation_steps"] == 0
    with open(cpath, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == EPISODE_FIELDS and len(rows) == 4
    assert [int(r["violation_steps"]) for r in rows] == \
        [r["violation_steps"] for r in data["episodes"]]
    assert math.isclose(float(rows[0]["return"]), data["episodes"][0]["return"], rel_tol=1e-12)


def test_single_learner_default_table(capsys):
    assert main(["evaluate", "--env", PM, "--learner", "none", "--agent", "random",
                 "--episodes", "1", "--max-steps", "20", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "none" in out and "Summary" in out


def test_limit_violations_are_counted_by_kind_and_printed(tmp_path, capsys):
    """Joint 1 swung at full torque without a filter exceeds its speed limit: the steps with
    ``info["limit_violation"]`` (counted by hand here) are the episode's ``limit_steps``, they
    are cost, and both tables show the kind."""
    from afvsgp_gym.evaluation import make_policy

    env_id = "afvsgp_gym/FrankaObstacleStatic-v0"
    env = gym.make(env_id)
    policy = make_policy("swing1", env, seed=0)
    obs, _ = env.reset(seed=0)
    limits = costs = 0
    for _ in range(300):
        obs, _, _, _, info = env.step(policy(obs))
        limits += info["limit_violation"]
        costs += info["cost"] > 0
    assert limits > 0 and costs >= limits
    jpath = tmp_path / "r.json"
    assert main(["evaluate", "--env", env_id, "--agent", "swing1", "--compare", "unfiltered",
                 "--episodes", "1", "--max-steps", "300", "--json", str(jpath),
                 "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "limits" in out and "w/ limits" in out and "range stop" in out
    data = json.loads(jpath.read_text())
    assert data["episodes"][0]["limit_steps"] == limits
    assert data["episodes"][0]["cost_steps"] == costs
    assert data["summary"]["unfiltered"]["episodes_with_limit_violation"] == 1


def test_default_learner_is_labelled_with_what_the_env_suggested(tmp_path, capsys):
    """``--learner`` defaults to "auto"; the report names the learner it resolved to (the
    point mass suggests none: the paper's per-barrier AFVSGP)."""
    jpath = tmp_path / "report.json"
    rc = main(["evaluate", "--env", PM, "--episodes", "1", "--max-steps", "40",
               "--json", str(jpath), "--no-progress"])
    assert rc == 0
    data = json.loads(jpath.read_text())
    assert list(data["summary"]) == ["auto (afvsgp)"]
    assert [r["learner"] for r in data["episodes"]] == ["auto (afvsgp)"]
    assert "auto (afvsgp)" in capsys.readouterr().out
