"""The reliability diagram of ``report --png``: its points from the records' calibration
counts, and the panel drawn for a real sweep with a learned band."""

from __future__ import annotations

import json
import struct

import pytest
from scipy.stats import norm

from afvsgp_gym.cli import main
from afvsgp_gym.sweep.plot import reliability_points
from afvsgp_gym.sweep.results import read_records

PM = "afvsgp_gym/PointMassObstacle-v0"


def _rec(n, miss, w1, w2, w3, **filter_kwargs):
    return {"config": {"filter_kwargs": filter_kwargs}, "calibration_samples": n,
            "calibration_misses": miss, "calibration_within_1std": w1,
            "calibration_within_2std": w2, "calibration_within_3std": w3}


def test_points_pool_the_pairs_of_every_episode():
    recs = [_rec(100, 2, 60, 90, 97), _rec(300, 1, 210, 285, 299), _rec(0, 0, 0, 0, 0)]
    promised, observed = reliability_points(recs)
    assert promised[:3] == pytest.approx([2 * norm.sf(k) for k in (1, 2, 3)], rel=1e-12)
    assert promised[3] == pytest.approx(norm.sf(2.5), rel=1e-12)  # the default beta
    assert observed == pytest.approx([130 / 400, 25 / 400, 4 / 400, 3 / 400], rel=1e-15)


def test_points_read_the_filters_promise():
    (promised, _), = [reliability_points([_rec(10, 0, 7, 9, 10, beta=2.0)])]
    assert promised[3] == pytest.approx(norm.sf(2.0), rel=1e-12)
    promised, _ = reliability_points([_rec(10, 0, 7, 9, 10, miss_probability=0.02)])
    assert promised[3] == pytest.approx(0.02, rel=1e-12)
    assert reliability_points([_rec(0, 0, 0, 0, 0)]) is None
    with pytest.raises(ValueError, match="different miss probabilities"):
        reliability_points([_rec(10, 0, 7, 9, 10), _rec(10, 0, 7, 9, 10, beta=3.0)])


def _png_width(path) -> int:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">I", data[16:20])[0]


def test_report_png_draws_the_band_of_a_learned_sweep(tmp_path, capsys):
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"grid": [
        {"envs": [PM], "learners": ["afvsgp", "oracle"], "seeds": [0], "max_steps": 500},
    ]}))
    out = tmp_path / "r.jsonl"
    assert main(["sweep", str(cfg), "--out", str(out), "--workers", "1", "--no-progress"]) == 0
    recs = read_records(out)
    learned = [r for r in recs if r["config"]["learner"] == "afvsgp"]
    assert learned[0]["calibration_samples"] > 0  # the learned band was scored
    promised, observed = reliability_points(learned)
    n = learned[0]["calibration_samples"]
    assert observed[3] == learned[0]["calibration_misses"] / n
    assert reliability_points([r for r in recs if r["config"]["learner"] == "oracle"]) is None
    with_band, without = tmp_path / "band.png", tmp_path / "plain.png"
    assert main(["report", str(out), "--png", str(with_band)]) == 0
    oracle_only = tmp_path / "oracle.jsonl"
    oracle_only.write_text("".join(json.dumps(r) + "\n" for r in recs
                                   if r["config"]["learner"] == "oracle"))
    assert main(["report", str(oracle_only), "--png", str(without)]) == 0
    capsys.readouterr()
    assert _png_width(with_band) > _png_width(without)  # the fourth panel
