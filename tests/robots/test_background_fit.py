"""The learners' warm-up fit in a process of its own (``BackgroundFit``): the bridge's loop
goes on while it runs, and what it installs is what the fit in the loop makes."""

import os

import numpy as np
import pytest

from afvsgp_gym.robots.background_fit import BackgroundFit
from afvsgp_gym.robots.terms import FEATURE_DIM

from .test_bridge import _bridge


def _commands(rec):
    return np.array([c[0] for c in rec.commands])


def test_the_fit_in_its_own_process_makes_the_loop_the_fit_in_the_loop_makes(monkeypatch):
    """With the worker's answer awaited (the one change: ``poll`` waits), the learners are
    installed at the tick the fit in ``observe`` would have fitted them, and the run is the
    same bit for bit: the same fitted learners (worker: a fresh interpreter, the samples
    through shared memory, the bank back through shared memory without a copy), the same
    commands."""
    seeded = {"seed": 3}  # the warm-up's exploration noise
    inline, rec_inline, _ = _bridge(agent="nominal", learner="afvsgp", filter_kwargs=seeded)
    a = inline.run(1.0)
    poll = BackgroundFit.poll
    monkeypatch.setattr(BackgroundFit, "poll", lambda self, wait=0.0: poll(self, 120.0))
    background, rec_bg, _ = _bridge(agent="nominal", learner="afvsgp", background_fit=True,
                                    filter_kwargs=seeded)
    b = background.run(1.0)
    assert a.stop_reason == b.stop_reason == "completed"
    assert a.fit_ticks is None and b.fit_ticks == 0 and b.fit_error is None
    assert not background.controller.warming_up and background.controller.fit_at_warmup
    np.testing.assert_array_equal(_commands(rec_inline), _commands(rec_bg))
    assert (a.filter_active_steps, a.min_h) == (b.filter_active_steps, b.min_h)
    # the installed learners' arrays live in the shared block and keep learning there
    block = background.controller.bank.bank.bank
    assert block._wk.flags.writeable and not block._wk.flags.owndata


def test_the_loop_goes_on_while_the_worker_fits():
    """Without waiting, the ticks after the warm-up run on (the filter as in the warm-up)
    until the fitted learners arrive, whenever that is."""
    bridge, _, _ = _bridge(agent="hold", learner="afvsgp", background_fit=True)
    report = bridge.run(0.6)
    assert report.stop_reason == "completed" and report.steps == 600
    if report.fit_ticks is None:  # still fitting when the run ended
        assert bridge.controller.warming_up
    else:
        assert 0 <= report.fit_ticks < 400 and not bridge.controller.warming_up


def test_a_failed_fit_is_reported_and_the_controller_stays_unfitted():
    bridge, _, _ = _bridge(agent="hold", learner="afvsgp")
    ctrl = bridge.controller
    ctrl.fit_at_warmup = False
    bridge.run(0.21)
    assert ctrl.warmup_complete
    ctrl._buffer = [(xi, u, np.full_like(z, np.nan)) for xi, u, z in ctrl._buffer]
    with BackgroundFit() as fitter:
        fitter.submit(ctrl)
        assert fitter.poll(120.0) is None
        assert "ValueError" in fitter.error and not fitter.pending
    assert ctrl.warming_up


def test_closing_mid_fit_stops_the_worker_and_leaves_no_shared_memory():
    bridge, _, _ = _bridge(agent="hold", learner="afvsgp")
    ctrl = bridge.controller
    ctrl.fit_at_warmup = False
    bridge.run(0.21)
    fitter = BackgroundFit().start(ctrl.warmup_shapes(ctrl.config.warmup_samples,
                                                      FEATURE_DIM))
    samples = fitter._samples.name
    fitter.submit(ctrl)
    process, result = fitter._process, fitter._result
    fitter.close()
    assert process.poll() is not None and not fitter.pending
    for name in (samples, result):
        assert not os.path.exists(f"/dev/shm/{name.lstrip('/')}")
    with pytest.raises(RuntimeError, match="before start"):
        fitter.submit(ctrl)


def test_a_lost_worker_is_reported_and_the_loop_goes_on(monkeypatch):
    """The worker killed before the samples go to it: the send fails inside the loop, which
    reports it (``fit_error``) and goes on with the learners unfitted."""
    start = BackgroundFit.start

    def start_then_lose(self, *args, **kwargs):
        start(self, *args, **kwargs)
        self._process.kill()
        self._process.wait(5.0)
        return self

    monkeypatch.setattr(BackgroundFit, "start", start_then_lose)
    bridge, _, _ = _bridge(agent="hold", learner="afvsgp", background_fit=True)
    report = bridge.run(0.4)
    assert report.stop_reason == "completed" and report.steps == 400
    assert report.fit_ticks is None and "Error" in report.fit_error
    assert bridge.controller.warming_up
