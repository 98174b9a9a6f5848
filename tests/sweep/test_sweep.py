"""Sweeps: identical records whatever the executor, worker count or order; resuming after a
kill neither repeats nor loses an episode; the report and evaluate --workers."""

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import afvsgp_gym
from afvsgp_gym.cli import main
from afvsgp_gym.evaluation import evaluate
from afvsgp_gym.sweep import (
    InlineExecutor,
    LocalExecutor,
    load_config,
    parse_config,
    read_records,
    run_sweep,
)

PM = "afvsgp_gym/PointMassObstacle-v0"
FR = "afvsgp_gym/FrankaObstacleDynamic-v0"
ROOT = Path(afvsgp_gym.__file__).resolve().parent.parent

#: Record columns that depend on the machine's timing, not on the episode.
TIMING = {"filter_time_median_s", "filter_time_p99_s", "filter_time_hist", "wall_s", "cpu_s",
          "host"}

MIXED = {"grid": [
    {"name": "pm", "envs": [PM], "learners": ["afvsgp", "none", "oracle"], "seeds": [0, 1],
     "max_steps": 400, "env_kwargs": {"scenario": ["dynamic", "random"]}},
    {"name": "pm_random_agent", "envs": [PM], "learners": ["afvsgp"], "agents": ["random"],
     "seeds": [5], "max_steps": 300},
    # the learned filter past its warm-up on the arm (chaotic: any numeric drift shows)
    # (the obstacle and limit barriers only: the self-collision pairs would double its time)
    {"name": "franka", "envs": [FR], "learners": ["afvsgp"], "seeds": [0, 1], "max_steps": 700,
     "env_kwargs": {"self_collision": [False]}},
]}


def _deterministic(record: dict) -> dict:
    return {k: v for k, v in record.items() if k not in TIMING}


def _by_key(records) -> dict:
    return {r["key"]: _deterministic(r) for r in records}


def test_serial_and_parallel_records_are_identical(tmp_path):
    episodes = parse_config(MIXED).episodes()
    shuffled = episodes[:]
    random.Random(3).shuffle(shuffled)
    serial = run_sweep(shuffled, tmp_path / "serial.jsonl", InlineExecutor(), progress=False)
    with LocalExecutor(2) as pool:
        parallel = run_sweep(episodes, tmp_path / "parallel.jsonl", pool, progress=False)
    assert serial.ran == parallel.ran == len(episodes) == 15
    a, b = _by_key(serial.records), _by_key(parallel.records)
    assert a == b  # every deterministic column, bit for bit (JSON floats round-trip)
    # the order of finishing differs, the content does not
    assert [r["key"] for r in serial.records] == [s.key() for _, s in shuffled]
    hosts = {r["host"] for r in parallel.records}
    assert len(hosts) == 1
    franka = [r for r in parallel.records if r["block"] == "franka"]
    for r in franka:  # past the learners' fit; the obstacle comes near only after step 700
        assert (r["steps"], r["cost_steps"], r["learner_error_steps"]) == (700, 0, 0), r
        assert r["min_h"] > 0.3 and r["interventions"] == 0, r
    assert franka[0]["return"] != franka[1]["return"]  # the seeds differ
    # which brake a record ran with: the Franka env's, none for the point mass's
    from afvsgp_gym.envs.franka import FrankaObstacleEnv

    assert {r.get("brake_version") for r in franka} == {FrankaObstacleEnv.BRAKE_VERSION}
    assert all("brake_version" not in r for r in parallel.records if r["block"] != "franka")


def test_resume_skips_finished_episodes(tmp_path, capsys):
    episodes = parse_config({"grid": [{"envs": [PM], "learners": ["none"],
                                       "seeds": {"start": 0, "count": 6},
                                       "max_steps": 100}]}).episodes()
    path = tmp_path / "r.jsonl"
    first = run_sweep(episodes, path, InlineExecutor(), progress=False, limit=4)  # a slice
    before = path.read_bytes()
    second = run_sweep(episodes, path, InlineExecutor(), progress=False)
    assert (first.ran, second.skipped, second.ran) == (4, 4, 2)
    assert path.read_bytes().startswith(before)  # nothing rewritten
    assert [r["key"] for r in read_records(path)] == [s.key() for _, s in episodes]
    third = run_sweep(episodes, path, InlineExecutor(), progress=False)
    assert (third.skipped, third.ran) == (6, 0)


def _children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


KILL_CONFIG = f"""
[[grid]]
envs = ["{PM}"]
learners = ["afvsgp", "oracle"]
seeds = {{start = 0, count = 14}}
max_steps = 300
[grid.env_kwargs]
scenario = ["dynamic"]
"""


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc")
@pytest.mark.parametrize("how", ["SIGKILL the process group", "SIGTERM the sweep"])
def test_killed_sweep_resumes_without_repeating_or_losing(tmp_path, capsys, how):
    cfg, out = tmp_path / "kill.toml", tmp_path / "r.jsonl"
    cfg.write_text(KILL_CONFIG)
    total = len(load_config(cfg).episodes())
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "afvsgp_gym.cli", "sweep", str(cfg), "--out", str(out),
         "--workers", "2", "--no-progress"],
        cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        start_new_session=True)
    deadline = time.monotonic() + 120
    while (not out.exists() or out.read_bytes().count(b"\n") < 5) and proc.poll() is None:
        assert time.monotonic() < deadline, "the sweep wrote nothing"
        time.sleep(0.05)
    assert proc.poll() is None, f"finished before the kill: {proc.stderr.read().decode()}"
    workers = _children(proc.pid)
    if how.startswith("SIGKILL"):
        os.killpg(proc.pid, signal.SIGKILL)
        assert proc.wait(30) == -signal.SIGKILL
    else:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 130  # interrupted cleanly
        assert b"re-run the same command" in proc.stderr.read()
        deadline = time.monotonic() + 10
        while any(_alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(_alive(p) for p in workers), "workers outlived the sweep"
    proc.stderr.close()
    kept = read_records(out)
    assert 5 <= len(kept) < total
    # a write cut short by the kill: the torn line must be tolerated
    with open(out, "ab") as fh:
        fh.write(out.read_bytes().splitlines()[0][:40])
    lines_before = out.read_bytes().splitlines()[: len(kept)]

    assert main(["sweep", str(cfg), "--out", str(out), "--workers", "2", "--no-progress"]) == 0
    text = capsys.readouterr()
    assert f"{total - len(kept)} episodes run, {len(kept)} already finished, 0 failed" \
        in text.out
    final = read_records(out)
    keys = [r["key"] for r in final]
    assert len(keys) == len(set(keys)) == total  # none repeated, none lost
    assert set(keys) == {s.key() for _, s in load_config(cfg).episodes()}
    assert out.read_bytes().splitlines()[: len(kept)] == lines_before  # finished kept as is


def test_report_cli_table_json_png(tmp_path, capsys):
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"grid": [
        {"envs": [PM], "learners": ["none", "oracle"], "seeds": [0, 1, 2], "max_steps": 600,
         "filter_kwargs": {"backup": [None]}},
    ]}))
    out = tmp_path / "r.jsonl"
    assert main(["sweep", str(cfg), "--out", str(out), "--workers", "1", "--no-progress"]) == 0
    capsys.readouterr()
    rjson, png = tmp_path / "rep.json", tmp_path / "rep.png"
    assert main(["report", str(out), "--json", str(rjson), "--png", str(png)]) == 0
    text = capsys.readouterr().out
    assert "w/ cost" in text and "cost<=95%" in text
    rep = json.loads(rjson.read_text())
    rows = {r["learner"]: r for r in rep["rows"]}
    records = read_records(out)
    for learner, row in rows.items():
        mine = [r for r in records if r["config"]["learner"] == learner]
        k = sum(r["cost_steps"] > 0 for r in mine)
        assert row["episodes"] == 3 and row["episodes_with_cost"] == k
        # the exact one-sided bound: P[Bin(3, p) <= k] = 0.05
        expected = 1 - 0.05 ** (1 / 3) if k == 0 else None
        if expected is not None:
            assert row["cost_rate_upper"] == pytest.approx(expected, rel=1e-12)
        assert row["min_h"] == pytest.approx(min(r["min_h"] for r in mine))
        assert row["contact_steps"] == sum(r["contact_steps"] for r in mine)
    # the nominal-only filter with the zero model and no backup violates; the oracle not
    assert rows["none"]["episodes_with_cost"] > 0 and rows["oracle"]["episodes_with_cost"] == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    assert main(["report", str(out), "--by", "env", "--markdown"]) == 0
    text = capsys.readouterr().out
    assert "|" in text and "6 episodes in 1 groups" in text
    with pytest.raises(SystemExit) as exc:
        main(["report", str(out), "--by", "colour"])
    assert exc.value.code == 2
    assert "unknown report field(s) ['colour']" in capsys.readouterr().err


def test_evaluate_workers_give_the_same_rows():
    kw = dict(learners=["afvsgp", "oracle"], episodes=2, seed=4, max_steps=400,
              env_kwargs={"scenario": "dynamic"})
    one = evaluate(PM, **kw)
    two = evaluate(PM, **kw, workers=2)
    strip = [{k: v for k, v in r.items() if not k.startswith("filter_time")}
             for r in one["episodes"]]
    assert strip == [{k: v for k, v in r.items() if not k.startswith("filter_time")}
                     for r in two["episodes"]]
    for name in ("afvsgp", "oracle"):
        a, b = one["summary"][name], two["summary"][name]
        assert {k: v for k, v in a.items() if not k.startswith("filter_time")} == \
            {k: v for k, v in b.items() if not k.startswith("filter_time")}


def test_failed_episodes_exit_1_and_are_retried(tmp_path, capsys, monkeypatch):
    """An episode that raises in a worker process of the local executor: the sweep records
    the others, prints the worker's traceback and its report, and exits with status 1; a
    re-run retries the failed episode only."""
    import afvsgp_gym.sweep

    # a value the pre-run check would refuse, let through so that the worker meets it
    monkeypatch.setattr(afvsgp_gym.sweep, "validate", lambda sweep: None)
    cfg, out = tmp_path / "c.json", tmp_path / "r.jsonl"
    cfg.write_text(json.dumps({"grid": [{"envs": [PM], "learners": ["none"], "seeds": [0],
                                         "max_steps": 20, "env_kwargs": {"mass": [1.0, -1.0]}}]}))
    argv = ["sweep", str(cfg), "--out", str(out), "--workers", "1", "--no-progress"]
    assert main(argv) == 1
    cap = capsys.readouterr()
    assert "LocalExecutor" in cap.out and "1 episodes run, 0 already finished, 1 failed" in cap.out
    assert "ValueError: mass must be" in cap.err and "1 episode(s) failed" in cap.err
    assert "w/ cost" in cap.out  # the finished episode's report
    records = read_records(out)
    assert [r["config"]["env_kwargs"]["mass"] for r in records] == [1.0]
    assert main(argv) == 1
    assert "0 episodes run, 1 already finished, 1 failed" in capsys.readouterr().out
    assert len(read_records(out)) == 1


@pytest.mark.parametrize("workers", [1, 2])
def test_evaluate_raises_the_episode_error_as_it_was(workers):
    with pytest.raises(ValueError, match="mass"):
        evaluate(PM, learners=["none"], episodes=2, max_steps=5, env_kwargs={"mass": -1.0},
                 workers=workers)


def _blas_env(queue) -> None:
    import os

    queue.put(os.environ.get("OPENBLAS_NUM_THREADS"))


def test_processes_started_in_one_blas_thread_get_one_blas_thread(monkeypatch):
    """Worker processes (sweep executors, SB3's SubprocVecEnv in `train`, the RL benchmark's
    evaluation pool) start with one BLAS thread; the parent's environment is restored."""
    import multiprocessing as mp

    from afvsgp_gym.executors import one_blas_thread

    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "4")
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    with one_blas_thread():
        p = ctx.Process(target=_blas_env, args=(q,))
        p.start()
    p.join(60)
    assert q.get(timeout=10) == "1"
    import os

    assert os.environ["OPENBLAS_NUM_THREADS"] == "4"
