"""Every docstring example of the package runs and prints what it shows: the modules are
found by their ``>>>`` lines (a new example is tested without being listed here)."""

import doctest
import importlib
from pathlib import Path

import pytest

import afvsgp_gym

PACKAGE = Path(afvsgp_gym.__file__).resolve().parent


def _modules_with_examples() -> list[str]:
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if ">>> " in path.read_text():
            parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
            names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


MODULES = _modules_with_examples()


def test_the_examples_are_found():
    # the wrappers' Example: sections (Gymnasium's habit) and the controller's module example
    for name in ("afvsgp_gym.wrappers.action_repeat", "afvsgp_gym.wrappers.episode_safety",
                 "afvsgp_gym.wrappers.safety_filter", "afvsgp_gym.cbf.controller"):
        assert name in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    res = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert res.attempted > 0 and res.failed == 0, res
