"""The README's Python examples, read from README.md and run as they are (the README cannot
drift from the code): what each prints is held to what the README says of it."""

import contextlib
import io
import re
from pathlib import Path

README = Path(__file__).resolve().parent.parent / "README.md"


def python_blocks() -> list[str]:
    """The fenced ``python`` blocks of README.md, in order."""
    return re.findall(r"^```python\n(.*?)^```$", README.read_text(), flags=re.S | re.M)


def _run(code: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, f"{README}:python block", "exec"), {"__name__": "__readme__"})
    return out.getvalue()


def test_the_readme_has_its_two_examples():
    blocks = python_blocks()
    assert len(blocks) == 2, [b.splitlines()[0] for b in blocks]
    assert "SafetyFilter" in blocks[0] and "SafetyController" in blocks[1]


def test_quick_start_runs_without_cost():
    """The first block: 300 steps of the moving obstacle behind the learned filter (its warm-up
    and the fit, with one BLAS thread as the README says: tests/conftest.py sets it), no cost."""
    printed = _run(python_blocks()[0])
    match = re.fullmatch(r"cost steps: (\d+), filter active: (True|False), h = (-?\d+\.\d{3}) m\n",
                         printed)
    assert match, printed
    assert int(match[1]) == 0 and float(match[3]) > 0.0


def test_without_a_simulator_keeps_the_cart_off_the_wall():
    """The second block: the cart driven at full speed at the wall stops short of it."""
    printed = _run(python_blocks()[1])
    match = re.fullmatch(r"closest approach to the wall: (-?\d+\.\d{3}) m, final x = "
                         r"(-?\d+\.\d{3}) m\n", printed)
    assert match, printed
    closest, final_x = float(match[1]), float(match[2])
    assert closest >= 0.0 and final_x < 1.0
    assert closest < 0.2  # it did drive up to the wall: the filter had something to stop

