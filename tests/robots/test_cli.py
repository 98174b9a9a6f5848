"""``afvsgp-gym robot``: the simulated run writes its counters; --host without pylibfranka
says how to install it; bad arguments name their option."""

import json
import sys

import pytest

from afvsgp_gym.cli import main
from afvsgp_gym.robots.libfranka import INSTALL_HINT


def test_simulate_writes_the_counters(tmp_path, capsys):
    path = tmp_path / "robot.json"
    status = main(["robot", "--simulate", "--seconds", "2", "--json", str(path)])
    out = json.loads(path.read_text())
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
    (["robot", "--simulate", "--agent", "ram"], "--agent"),
    (["robot", "--simulate", "--learner", "nope"], "--learner"),
    (["robot", "--simulate", "--learner", "oracle"], "--learner oracle needs the true terms"),
    (["robot", "--simulate", "--torque-error", "1,2"], "--torque-error"),
    (["robot", "--simulate", "--budget", "2"], "--budget"),
    (["robot", "--host", "1.2.3.4", "--obstacle", "0.5,0,0.4"], "--obstacle"),
    (["robot", "--simulate", "--rt-priority", "0"], "--rt-priority"),
])
def test_bad_arguments_exit_2_naming_the_option(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
