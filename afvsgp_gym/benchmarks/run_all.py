"""Every benchmark area in one run (``afvsgp-gym bench`` / ``python -m
afvsgp_gym.benchmarks.run_all [--quick]``).

One public function, :func:`run_all`: imports ``afvsgp_gym.benchmarks.<area>`` for each area,
calls its ``run(quick)`` and prints the figures (times ending in ``_s`` shown in microseconds
below one second).
An area whose module is missing or fails is reported and skipped; the others still run.
"""

from __future__ import annotations

import importlib
import sys
import time
import traceback
from collections.abc import Sequence

from afvsgp_gym.benchmarks._machine import machine

__all__ = ["AREAS", "main", "run_all"]

AREAS = ("gp", "envs", "filter", "arm", "solver", "sweep")


def _format(key: str, val) -> str:
    if not isinstance(val, int | float):
        return str(val)
    if key.endswith("_s"):  # seconds: microseconds unless a second or more
        return f"{val:12.2f} s " if val >= 1.0 else f"{val * 1e6:12.1f} us"
    return f"{val:12.4g}"


def run_all(quick: bool = False, areas: Sequence[str] | None = None,
            out=None) -> dict[str, dict | None]:
    """Run the areas (default all); returns ``{area: results or None if missing/failed}``."""
    out = out or sys.stdout
    areas = list(AREAS if areas is None else areas)
    unknown = [a for a in areas if a not in AREAS]
    if unknown:
        raise ValueError(f"unknown benchmark area(s) {unknown}; valid: {list(AREAS)}")
    print(f"afvsgp-gym benchmarks ({'quick' if quick else 'full'}) on {machine()}",
          file=out, flush=True)
    results: dict[str, dict | None] = {}
    for area in areas:
        name = f"afvsgp_gym.benchmarks.{area}"
        print(f"\n== {area} ==", file=out, flush=True)
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            print(f"skipped: module {name} is not present (not implemented yet)", file=out)
            results[area] = None
            continue
        t0 = time.perf_counter()
        try:
            res = mod.run(quick=quick)
        except Exception:  # one failing area must not hide the others
            print(f"FAILED: {name}.run raised:\n{traceback.format_exc()}", file=out)
            results[area] = None
            continue
        width = max((len(k) for k in res), default=0)
        for key, val in res.items():
            print(f"  {key:<{width}}  {_format(key, val)}", file=out)
        print(f"  ({time.perf_counter() - t0:.1f} s)", file=out, flush=True)
        results[area] = res
    return results


def main(argv: list[str] | None = None) -> None:
    import argparse

    parser = argparse.ArgumentParser(description="every benchmark area's figures")
    parser.add_argument("--quick", action="store_true", help="smaller runs")
    run_all(quick=parser.parse_args(argv).quick)


if __name__ == "__main__":
    main()
