"""The RL benchmark's --quick form end to end (a test of the pipeline, not of the result),
and its pure helpers."""

import json

import numpy as np
import pytest
import rl_benchmark as rl  # benchmarks/rl_benchmark.py (pytest's pythonpath)


@pytest.mark.parametrize("k, n", [(45, 50), (0, 10), (10, 10), (1, 3), (37, 200)])
def test_wilson_interval_against_scipy(k, n):
    """Against scipy's Wilson score interval (``binomtest(...).proportion_ci``, its own z of
    the 95 % level); the benchmark's default z = 1.96 moves the ends by less than 1e-4."""
    from scipy.stats import binomtest, norm

    ref = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    lo, hi = rl._wilson(k, n, z=float(norm.ppf(0.975)))
    assert lo == pytest.approx(ref.low, rel=1e-12, abs=1e-15)
    assert hi == pytest.approx(ref.high, rel=1e-12, abs=1e-15)
    np.testing.assert_allclose(rl._wilson(k, n), (ref.low, ref.high), atol=1e-4)



def test_curves_bin_by_agent_steps():
    eps = [{"timesteps": t, "return": r, "success": s, "cost_steps": c,
            "cost_steps_after_warmup": a}
           for t, r, s, c, a in [(10, 1.0, 0, 5, 0), (40, 3.0, 1, 0, 0), (60, 2.0, 1, 2, 2),
                                 (100, 4.0, 0, 1, 1)]]
    cur = rl._curves(eps, 100, 2)
    assert cur["steps"] == [50.0, 100.0]
    assert cur["return"] == [2.0, 3.0] and cur["success"] == [0.5, 0.5]
    assert cur["cumulative_cost"] == [5.0, 8.0]
    assert cur["cumulative_cost_after_warmup"] == [0.0, 3.0]


@pytest.mark.slow
def test_quick_benchmark_pipeline(tmp_path):
    pytest.importorskip("stable_baselines3", reason="needs the rl extra")
    from dataclasses import replace

    from afvsgp_gym.agents.sb3 import load_policy

    # the filtered conditions train behind a non-default filter; the evaluation runs the default
    cfg = replace(rl.RLBenchConfig.quick(), filter_kwargs={"online_exploration": 0.05})
    res = rl.run(cfg, tmp_path, log=lambda m: None)
    data = json.loads((tmp_path / "rl_results.json").read_text())
    assert len(data["runs"]) == len(cfg.conditions) * len(cfg.seeds)
    for r in data["runs"]:
        assert r["timesteps"] == cfg.timesteps
        assert r["env_steps"] == 10 * cfg.timesteps
        cum = np.array(r["curves"]["cumulative_cost"])
        assert np.all(np.diff(cum) >= 0) and cum[-1] == r["training"]["cost_steps"]
        assert r["eval_own"]["episodes"] == cfg.eval_episodes
        assert r["eval_afvsgp_kept"]["episodes"] == cfg.eval_episodes
        trained_behind = load_policy(r["zip"]).meta["filter_kwargs"]
        assert trained_behind == ({} if r["condition"] == "unfiltered"
                                  else {"online_exploration": 0.05})
        if r["condition"] == "afvsgp":
            # the learner's warm-up happened in training, once per worker
            assert r["training"]["warmup_steps"] == cfg.n_envs * 75
        else:  # the oracle and the bare env have nothing to learn
            assert r["training"]["warmup_steps"] == 0
    table = (tmp_path / "rl_table.md").read_text()
    for cond in cfg.conditions:
        assert f"| {cond} |" in table
    assert (tmp_path / "rl_training.png").stat().st_size > 10_000
    assert res["total_wall_s"] > 0


@pytest.mark.parametrize("value, message", [
    ("[0.05]", "--filter-kwargs must be a JSON object"),
    ("{online_exploration: 0.05}", "--filter-kwargs must be a JSON object"),
    ('{"online_exploraton": 0.05}', "unknown SafetyFilter option(s) ['online_exploraton']"),
])
def test_bad_filter_kwargs_are_refused_before_anything_runs(capsys, value, message):
    with pytest.raises(SystemExit) as exc:
        rl.main(["--quick", "--filter-kwargs", value])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
