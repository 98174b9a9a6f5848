"""``afvsgp-gym robot``: the simulated run writes its counters; --host without pylibfranka
says how to install it; bad arguments name their option."""

import json
import os
import sys
import types

import pytest

from afvsgp_gym.cli import main
from afvsgp_gym.robots.libfranka import INSTALL_HINT


@pytest.mark.parametrize("priority", [None, "0"])
def test_simulate_writes_the_counters(tmp_path, capsys, priority):
    """By default the loop asks for SCHED_FIFO 50 (normal priority where the system refuses,
    said in ``scheduler``); ``--rt-priority 0`` runs at normal priority."""
    path = tmp_path / "robot.json"
    extra = [] if priority is None else ["--rt-priority", priority]
    status = main(["robot", "--simulate", "--seconds", "2", "--json", str(path), *extra])
    out = json.loads(path.read_text())
    if priority is None:
        assert out["scheduler"] == "SCHED_FIFO 50" or "SCHED_FIFO 50 refused" in out["scheduler"]
    else:
        assert out["scheduler"] == "SCHED_OTHER"
    for key in ("steps", "rate_hz", "deadline_misses", "cost_steps", "step_time_ms",
                "stop_reason", "machine", "scheduler"):
        assert key in out
    assert {"p50", "p99", "p99.9", "max"} <= set(out["step_time_ms"])
    assert out["mode"] == "simulate" and out["steps"] > 0
    # a run the machine's load cut short (the stand-in's lost-command check) exits 1
    assert status == (0 if out["stop_reason"] == "completed" else 1)
    assert "steps in" in capsys.readouterr().out


def test_host_without_pylibfranka_says_how_to_install_it(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "pylibfranka", None)  # import fails as when absent
    with pytest.raises(SystemExit) as exc:
        main(["robot", "--host", "172.16.0.2", "--seconds", "1"])
    assert exc.value.code == 3  # the package's status for a missing optional extra
    err = capsys.readouterr().err
    assert INSTALL_HINT in err and "afvsgp-gym[robot]" in err


@pytest.mark.parametrize("argv, message", [
    (["robot"], "exactly one of --simulate and --host"),
    (["robot", "--simulate", "--host", "1.2.3.4"], "exactly one of --simulate and --host"),
    (["robot", "--simulate", "--seconds", "0"], "--seconds"),
    (["robot", "--simulate", "--agent", "greedy"], "--agent"),
    (["robot", "--simulate", "--agent", "swing2", "--seed", "-3"], "--seed must be >= 0"),
    (["robot", "--simulate", "--learner", "nope"], "--learner"),
    (["robot", "--simulate", "--learner", "oracle"], "--learner oracle needs the true terms"),
    (["robot", "--simulate", "--torque-error", "1,2"], "--torque-error"),
    (["robot", "--simulate", "--budget", "2"], "--budget"),
    (["robot", "--host", "1.2.3.4", "--obstacle", "0.5,0,0.4"], "--obstacle"),
    (["robot", "--simulate", "--obstacles", '{"type": "plane"}'],
     "--obstacles must be a JSON list of objects"),
    (["robot", "--simulate", "--obstacles", "[{"], "--obstacles must be a JSON list"),
    (["robot", "--host", "1.2.3.4", "--obstacles", '[{"type": "cone", "position": [0, 0, 0]}]'],
     "--obstacles: obstacles[0]['type'] must be one of"),
    (["robot", "--simulate", "--obstacles",
      '[{"type": "box", "position": [0.5, 0, 0.2], "half_sizes": [0.1, 0, 0.1]}]'],
     "--obstacles: obstacles[0]['half_sizes'] must be > 0"),
    (["robot", "--simulate", "--obstacles",
      '[{"type": "capsule", "position": [0.5, NaN, 0.2], "radius": 0.02, "half_length": 0.1}]'],
     "--obstacles: obstacles[0]['position'] must be finite"),
    (["robot", "--simulate", "--rt-priority", "100"], "--rt-priority"),
    (["robot", "--simulate", "--rt-priority", "-1"], "--rt-priority"),
])
def test_bad_arguments_exit_2_naming_the_option(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_simulate_takes_typed_obstacles_as_the_envs_do(tmp_path):
    """A table at the mount, a box and a sphere beside the path replace the stand-in's
    moving sphere: the closest barrier is link 1's lowest sphere over the table (its centre
    turns about the vertical axis only: its lowest point 0.1128 m above the mount), nearer
    than the others and than the moving sphere would have been."""
    path = tmp_path / "robot.json"
    table = {"type": "plane", "position": [0, 0, 0], "normal": [0, 0, 1]}
    box = {"type": "box", "position": [0.45, 0.3, 0.3], "half_sizes": [0.05, 0.05, 0.05],
           "quat": [0.98, 0.0, 0.0, 0.2]}
    status = main(["robot", "--simulate", "--seconds", "1", "--obstacles",
                   json.dumps([table, box]), "--obstacle", "0.3,-0.35,0.5,0.04",
                   "--json", str(path)])
    out = json.loads(path.read_text())
    assert out["mode"] == "simulate" and out["steps"] > 0
    assert status == (0 if out["stop_reason"] == "completed" else 1)
    assert out["min_h"] == pytest.approx(0.1128, abs=1e-6)


def _refuse_realtime(monkeypatch):
    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")
    monkeypatch.setattr(os, "sched_setscheduler", refuse)


def test_a_refused_priority_stops_the_robot_and_not_the_dry_run(monkeypatch, capsys):
    """As libfranka's default (kEnforce), ``--host`` does not start a loop the system refuses
    a real-time priority, and says how to run anyway; ``realtime_priority`` without
    ``enforce`` (the stand-in's dry run) runs on at normal priority and says why."""
    from afvsgp_gym.robots.run import realtime_priority

    _refuse_realtime(monkeypatch)
    with realtime_priority(50) as scheduler:
        assert scheduler.startswith("SCHED_OTHER (SCHED_FIFO 50 refused")
    with pytest.raises(RuntimeError, match="--rt-priority 0"):
        with realtime_priority(50, enforce=True):
            pass
    # the bindings stand in for the robot's (never called: the loop stops before connecting)
    monkeypatch.setitem(sys.modules, "pylibfranka", types.ModuleType("pylibfranka"))
    assert main(["robot", "--host", "172.16.0.2", "--seconds", "1"]) == 1
    err = capsys.readouterr().err
    assert "SCHED_FIFO 50 refused" in err and "--rt-priority 0" in err
