"""The warm-up fit inside the filter loop: ``benchmarks/gp_fit.py``'s probe sees the fitted
learner once, right after warm-up (its conditioning report)."""

import numpy as np
from gp_fit import conditioning  # benchmarks/gp_fit.py (pytest's pythonpath)

from afvsgp_gym.benchmarks.filter import run_episode


def test_probe_reports_conditioning_after_the_warm_up_fit():
    calls = []

    def probe(controller):
        assert not controller.warming_up
        calls.append(int(controller.bank.bank.n_seen_[0]))
        return conditioning(controller)

    res = run_episode("pointmass", "afvsgp", 0, probe=probe)
    assert len(calls) == 1 and calls[0] >= 2  # once, right after the fit on the warm-up data
    assert res["cond_koo"] >= 1.0 and res["cond_sig"] >= 1.0 and np.isfinite(res["cond_sig"])
    assert res["noise"] > 0
    unfiltered = run_episode("pointmass", None, 0, probe=probe)
    assert "cond_koo" not in unfiltered and len(calls) == 1
