"""Test-wide settings: headless MuJoCo rendering, one BLAS thread.

Small-matrix LAPACK calls (M = 20) are dominated by thread hand-off on a shared 2-core
machine; one BLAS thread keeps the suite fast and its timings meaningful.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
