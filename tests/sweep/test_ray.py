"""The Ray executor on a local Ray instance gives the local executor's records (skipped when
ray, the 'cluster' extra, is not installed)."""

import json
import sys

import pytest

from afvsgp_gym.cli import main
from afvsgp_gym.sweep import InlineExecutor, RayExecutor, parse_config, run_sweep

PM = "afvsgp_gym/PointMassObstacle-v0"
TIMING = {"filter_time_median_s", "filter_time_p99_s", "filter_time_hist", "wall_s", "cpu_s",
          "host"}

TINY = {"grid": [{"envs": [PM], "learners": ["afvsgp", "none"], "seeds": [0, 1, 2],
                  "max_steps": 300, "env_kwargs": {"scenario": ["dynamic"]}}]}


@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, local_mode=False,
             configure_logging=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def test_ray_executor_matches_the_local_executor(ray_instance, tmp_path):
    episodes = parse_config(TINY).episodes()
    local = run_sweep(episodes, tmp_path / "local.jsonl", InlineExecutor(), progress=False)
    with RayExecutor() as executor:  # uses the running instance, leaves it open
        assert executor.workers == 2
        remote = run_sweep(episodes, tmp_path / "ray.jsonl", executor, progress=False)
    assert ray_instance.is_initialized()
    assert remote.ran == local.ran == len(episodes) == 6 and not remote.failed

    def strip(records):
        return {r["key"]: {k: v for k, v in r.items() if k not in TIMING} for r in records}

    assert strip(remote.records) == strip(local.records)


def test_ray_task_errors_come_back_as_failures(ray_instance, tmp_path):
    bad = parse_config({"grid": [{"envs": [PM], "learners": ["none"], "seeds": [0],
                                  "env_kwargs": {"mass": [-1.0]}}]}).episodes()
    with RayExecutor() as executor:
        res = run_sweep(bad, tmp_path / "r.jsonl", executor, progress=False, log=lambda m: None)
    assert res.ran == 0 and len(res.failed) == 1 and "mass" in res.failed[0][1]
    assert (tmp_path / "r.jsonl").read_text() == ""  # a failure is not a result


def test_missing_ray_names_the_extra(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # as if ray were not installed
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"grid": [{"envs": [PM], "learners": ["none"], "seeds": [0]}]}))
    with pytest.raises(SystemExit) as exc:
        main(["sweep", str(cfg), "--ray", "auto", "--out", str(tmp_path / "r.jsonl")])
    assert exc.value.code == 3
    assert "afvsgp-gym[cluster]" in capsys.readouterr().err
