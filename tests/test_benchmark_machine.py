"""The machine line and speed calibration printed with every benchmark."""

import math
import os

import pytest

from afvsgp_gym._compiled import extension
from afvsgp_gym.benchmarks._machine import calibration, calibration_line, machine


def test_machine_names_cores_python_and_the_learners_core_in_use():
    line = machine()
    assert f"{os.cpu_count()} cores" in line
    assert "Python 3." in line
    core = extension("bank")
    if core is not None:
        assert line.endswith(f"learners' core {core.simd()[0]}")


def test_calibration_gives_three_positive_costs():
    cal = calibration(repeat=2)
    assert set(cal) == {"numpy call ns", "float64 exp ns/element", "cholesky 40x40 us"}
    assert all(math.isfinite(v) and v > 0.0 for v in cal.values())
    assert calibration_line().startswith("calibration: numpy call ns ")


@pytest.mark.parametrize("bad", [0, -1, 2.5, True, None])
def test_calibration_rejects_a_bad_repeat(bad):
    with pytest.raises(ValueError, match="repeat"):
        calibration(repeat=bad)
