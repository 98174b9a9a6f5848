"""One-line description of the machine a benchmark ran on, and what its speed is made of."""

from __future__ import annotations

import os
import platform
import timeit

import numpy as np


def machine() -> str:
    """CPU model name (from /proc/cpuinfo where present), core count, Python version, whether
    numpy runs AVX-512 kernels on it (its float64 ``exp`` is vectorised only there) and which
    copy of the learners' compiled hot loops runs."""
    from afvsgp_gym.evaluation import cpu_model

    out = f"{cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}"
    avx512 = _numpy_avx512()
    if avx512 is not None:
        out += f", numpy AVX-512 {'yes' if avx512 else 'no'}"
    simd = _learners_core_simd()
    return out if simd is None else f"{out}, learners' core {simd}"


def _learners_core_simd() -> str | None:
    """The copy of the learners' compiled hot loops in use ('avx512f', 'avx2', 'base'); None
    without the compiled core."""
    from afvsgp_gym._compiled import extension

    core = extension("bank")
    return None if core is None else core.simd()[0]


def _numpy_avx512() -> bool | None:
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as features
    except ImportError:
        try:
            from numpy.core._multiarray_umath import __cpu_features__ as features
        except ImportError:
            return None
    return bool(features.get("AVX512F", False))


def calibration(repeat: int = 7) -> dict[str, float]:
    """The three costs the filtered step is made of, each the best of ``repeat`` timings
    (the least disturbed by other load): one small numpy call (``a + a``, 8 elements, ns),
    float64 ``exp`` per element (6,720 values in [-20, 0], the learners' kernel block, ns)
    and the Cholesky factor of a 40 x 40 matrix (``np.linalg.cholesky``, us). Compare
    absolute times between machines through these, not through the CPU's name."""
    if isinstance(repeat, bool) or not isinstance(repeat, int) or repeat < 1:
        raise ValueError(f"repeat must be an integer >= 1. Got: {repeat!r}")
    rng = np.random.default_rng(0)
    small = np.ones(8)
    expo = -20.0 * rng.random(6720)
    a = rng.standard_normal((40, 40))
    spd = a @ a.T + 40.0 * np.eye(40)

    def best(fn, number: int) -> float:
        return min(timeit.repeat(fn, number=number, repeat=repeat)) / number

    return {
        "numpy call ns": best(lambda: small + small, 2000) * 1e9,
        "float64 exp ns/element": best(lambda: np.exp(expo), 50) / expo.size * 1e9,
        "cholesky 40x40 us": best(lambda: np.linalg.cholesky(spd), 200) * 1e6,
    }


def calibration_line() -> str:
    """:func:`calibration` as one line."""
    return "calibration: " + ", ".join(f"{k} {v:.1f}" for k, v in calibration().items())
