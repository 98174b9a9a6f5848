"""Test-wide settings: headless MuJoCo rendering, one BLAS thread.

Small-matrix LAPACK calls (M = 20) are dominated by thread hand-off on a shared 2-core
machine; one BLAS thread keeps the suite fast and its timings meaningful.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


import pytest  # noqa: E402

from afvsgp_gym import _compiled  # noqa: E402


@pytest.fixture
def without_extensions(monkeypatch):
    """``hide(*names)``: the compiled extensions ``names`` (``"cones"``, ``"step"``,
    ``"bank"``, ``"arm"``) count as not built for the rest of the test (as installed without a C
    compiler), for the backends resolved from then on."""

    def hide(*names):
        for name in names:
            monkeypatch.setitem(_compiled._loaded, name, None)

    return hide
