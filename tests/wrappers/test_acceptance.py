"""Issue 4 acceptance with the nominal "zero" model (real simulators, seeded episodes).

The point mass runs all 20 seeds; the Franka runs seed 0 per learner and scenario here (the
10-seed sweeps are in ``afvsgp_gym.benchmarks.filter``; measured results and the seeds that
fail are reported in benchmarks/filter.md). Tracking "away from the obstacle" is |p - r| (m)
at the steps where the reference keeps >= 5 cm outside every obstacle's safe set
(``run_episode``); "bounded" is asserted as fixed limits (the unfiltered tracker's own error
is 3-5 cm; the filtered arm may detour or stop behind the obstacle for a while).
"""

import pytest

from afvsgp_gym.benchmarks.filter import run_episode


def test_pointmass_none_violates():
    # without the brake backup: on the point mass the env's brake alone keeps "none" safe
    # (benchmarks/filter.md), so the nominal-only HOCBF is judged on its own here
    assert run_episode("pointmass", "none", seed=0, backup=None)["violations"] > 0


def test_pointmass_afvsgp_zero_violations_20_seeds():
    rows = [run_episode("pointmass", "afvsgp", seed=s) for s in range(20)]
    assert [r["violations"] for r in rows] == [0.0] * 20
    assert min(r["min_h"] for r in rows) >= 0.0
    assert max(r["track_max"] for r in rows) < 0.3


@pytest.mark.parametrize("scenario", ["franka_static", "franka_dynamic"])
def test_franka_none_violates(scenario):
    assert run_episode(scenario, "none", seed=0)["violations"] > 0


@pytest.mark.parametrize("scenario", ["franka_static", "franka_dynamic"])
@pytest.mark.parametrize("learner", ["oracle", "afvsgp"])
def test_franka_zero_violations_and_bounded_tracking(scenario, learner):
    r = run_episode(scenario, learner, seed=0)
    assert r["violations"] == 0 and r["min_h"] >= 0.0
    assert r["track_mean"] < 0.15 and r["track_max"] < 0.75
