"""Fixtures of the GP tests."""

import pytest

from afvsgp_gym.gp import afvsgp_bank


@pytest.fixture
def restore_simd():
    """Puts the compiled core's own choice of hot-loop copy back after the test (which may
    switch it with ``_bank.simd(name)``)."""
    core = afvsgp_bank._core
    if core is None:
        yield
        return
    in_use = core.simd()[0]
    yield
    core.simd(in_use)
