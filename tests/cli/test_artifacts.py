"""plot / video / reproduce machinery / bench on small configurations."""

import json
import sys

import imageio.v2 as imageio
import numpy as np
import pytest

from afvsgp_gym.benchmarks.run_all import run_all
from afvsgp_gym.cli import main
from afvsgp_gym.plotting import plot_barrier, plot_uncertainty
from afvsgp_gym.reproduce import ReproduceConfig, reproduce

PM = "afvsgp_gym/PointMassObstacle-v0"
PNG = b"\x89PNG\r\n\x1a\n"


def _is_png(path) -> bool:
    return path.is_file() and path.read_bytes()[:8] == PNG and path.stat().st_size > 1000


def test_plots_from_arrays_are_valid_pngs(tmp_path):
    t = np.linspace(0.0, 5.0, 200)
    s = {"A": {"t": t, "truth": np.sin(t), "mean": np.sin(t) + 0.1, "std": 0.1 + 0 * t}}
    p = plot_uncertainty(s, tmp_path / "f2.png", switch_time=2.5)
    assert _is_png(p)
    p = plot_barrier({"A": {"t": t, "h": np.cos(t)}}, tmp_path / "f4.png", margin=0.07)
    assert _is_png(p)


def test_reproduce_tiny_then_plot(tmp_path, capsys):
    cfg = ReproduceConfig(static_env=PM, dynamic_env=PM, env_kwargs={},
                          dynamic_env_kwargs={"scenario": "dynamic"}, n_prelim=30,
                          n_offline=80, stream_start=860, stream_end=960,
                          dynamic_learners=("none", "afvsgp", "oracle"), dynamic_episodes=1,
                          dynamic_max_steps=450)
    res = reproduce(cfg, out_dir=tmp_path / "docs")
    data = json.loads((tmp_path / "docs" / "reproduce.json").read_text())
    assert set(data) == {"table1", "dynamic", "margin", "dynamic_arm"}
    assert set(data["table1"]) == {"afvsgp", "vsgp", "gp", "sogp"}
    for name, row in data["table1"].items():
        assert row["mse"] >= 0 and row["n_stream"] == 100
        assert (row["update_time_s"] is None) == (name == "gp")
    assert data["table1"]["afvsgp"]["n_fit"] == 30 and data["table1"]["vsgp"]["n_fit"] == 80
    for name in ("none", "afvsgp", "oracle"):
        assert {"violations", "min_h"} <= set(data["dynamic"][name])
    m = data["margin"]
    assert m["conservatism"] == m["afvsgp_min_h"] - m["oracle_min_h"]
    assert res["table1"]["gp"]["mse"] == data["table1"]["gp"]["mse"]
    for name in ("fig2_uncertainty.png", "fig4_barrier.png", "fig6_margin.png"):
        assert _is_png(tmp_path / "docs" / name)
    assert "| AFVSGP (ours) |" in (tmp_path / "docs" / "table1.md").read_text()
    # `plot` re-renders from the saved traces
    assert main(["plot", "--traces", str(tmp_path / "docs"), "--out", str(tmp_path / "re")]) == 0
    assert _is_png(tmp_path / "re" / "fig2_uncertainty.png")
    assert "wrote" in capsys.readouterr().out


def test_plot_without_traces_explains(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["plot", "--traces", str(tmp_path)])
    assert exc.value.code == 2
    assert "afvsgp-gym reproduce" in capsys.readouterr().err


def test_video_gif_and_mp4(tmp_path, capsys):
    for name in ("ep.gif", "ep.mp4"):
        path = tmp_path / name
        assert main(["video", "--env", PM, "--learner", "none", "--max-steps", "30",
                     "--every", "3", "--out", str(path)]) == 0
        if name.endswith(".gif"):
            frames = imageio.mimread(path)
            assert len(frames) == 11 and frames[0].ndim == 3
        else:
            head = path.read_bytes()[:12]
            assert head[4:8] == b"ftyp" and path.stat().st_size > 1000  # an MP4 container


def test_bench_tolerates_a_missing_module(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "afvsgp_gym.benchmarks.envs", None)  # as if absent
    res = run_all(quick=True, areas=["envs"])
    assert res == {"envs": None}
    assert "afvsgp_gym.benchmarks.envs is not present" in capsys.readouterr().out
    # bench exits with status 1 when no area it was asked for ran
    assert main(["bench", "--quick", "--only", "envs"]) == 1
    assert "afvsgp_gym.benchmarks.envs is not present" in capsys.readouterr().out
