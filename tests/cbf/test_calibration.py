"""The learned band's calibration: scores and counts, the conformal multiplier's guarantee on
synthetic streams, and the filter's report of the band it used (``delta_b_lower``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtri
from scipy.stats import norm

from afvsgp_gym.cbf import SafetyController
from afvsgp_gym.cbf.calibration import (
    ConformalMultiplier,
    beta_for_miss_probability,
    miss_target,
    near_binding,
    score_counts,
)
from afvsgp_gym.cbf.config import FilterConfig
from afvsgp_gym.types import BarrierTerms

BETA, ETA = 2.5, 0.5


@pytest.mark.parametrize("beta", [0.0, 1.0, 2.5, 6.0, 9.0])
def test_miss_target_is_the_normal_tail(beta):
    assert miss_target(beta) == pytest.approx(norm.sf(beta), rel=1e-12)


@pytest.mark.parametrize("p", [1e-15, 1e-9, 1e-4, miss_target(2.5), 0.1, 0.3, 0.5])
def test_miss_probability_gives_the_normal_quantile(p):
    """Against scipy's ndtri (cephes, another algorithm), in the tail too: ``-ndtri(p)``,
    never ``ndtri(1 - p)``, which loses ``p`` below 1e-16. d beta / d ln p = -1 / (beta's
    hazard) is at most ~1 / beta, so 1e-12 relative in p is far below 1e-10 in beta."""
    beta = beta_for_miss_probability(p)
    assert beta == pytest.approx(max(0.0, -ndtri(p)), rel=1e-10, abs=1e-12)
    assert miss_target(beta) == pytest.approx(p, rel=1e-9)


@pytest.mark.parametrize("p", [0.0, -0.1, 0.51, 1.0, float("nan"), "a", None])
def test_bad_miss_probability_is_refused_by_name(p):
    with pytest.raises(ValueError, match="miss_probability"):
        beta_for_miss_probability(p)


def test_controller_takes_a_miss_probability_for_beta():
    ctrl = SafetyController(-np.ones(2), np.ones(2), n_barriers=2, miss_probability=0.01)
    assert ctrl.config.beta == pytest.approx(norm.isf(0.01), rel=1e-10)
    assert ctrl.config.miss_probability == pytest.approx(0.01, rel=1e-10)
    assert SafetyController(-np.ones(2), np.ones(2), miss_probability=0.5).config.beta == 0.0
    with pytest.raises(ValueError, match="beta or miss_probability"):
        SafetyController(-np.ones(2), np.ones(2), beta=2.0, miss_probability=0.01)
    with pytest.raises(ValueError, match="miss_probability"):
        SafetyController(-np.ones(2), np.ones(2), miss_probability=0.7)


def test_score_counts_by_hand():
    z = np.array([0.0, -3.0, 2.5, np.nan, 1.0, -0.5])
    mean = np.array([0.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    std = np.array([1.0, 1.0, 1.0, 1.0, 0.0, 0.25])
    lower = mean - 2.5 * std
    e, c = score_counts(z, mean, std, lower)
    # scores 0, -3, 2.5, (NaN: z), (NaN: std 0), -2
    np.testing.assert_array_equal(np.isnan(e), [False, False, False, True, True, False])
    assert c.samples == 4
    assert c.misses == 1  # only -3 < -2.5
    assert (c.within_1std, c.within_2std, c.within_3std) == (1, 2, 4)
    assert (c.near_samples, c.near_misses) == (0, 0)  # not told which rows are near binding
    # near binding: margin below the band's width (center - lower = 2.5 std); NaN is not
    margin = np.array([0.1, 2.0, 3.0, 0.0, 0.0, np.nan])
    near = near_binding(margin, mean, lower)
    np.testing.assert_array_equal(near, [True, True, False, True, False, False])
    _, c = score_counts(z, mean, std, lower, near)
    # scored and near: rows 0 and 1 (row 3 has no score, row 4 a zero std); row 1 missed
    assert (c.near_samples, c.near_misses) == (2, 1)
    assert c[:5] == score_counts(z, mean, std, lower)[1][:5]


def _stream(q_model, scores_per_step):
    """Run a ConformalMultiplier over a stream of score rows, each judged against the
    multiplier in force; returns (misses, samples, time-average of q)."""
    cm = q_model
    misses = samples = 0
    q_sum = np.zeros_like(cm.q)
    for scores in scores_per_step:
        rows = np.arange(len(scores))
        misses += int((scores < -cm.multiplier(rows)).sum())
        samples += len(scores)
        q_sum += cm.q
        cm.update(rows, scores)
    return misses, samples, q_sum / len(scores_per_step)


def test_deterministic_bound_on_an_adversarial_stream():
    """Scores built to miss as often as possible (each just below the current band, while
    the band is below Q): misses <= alpha N + (Q - beta + eta n) / eta, the module's bound."""
    cm = ConformalMultiplier(np.zeros(2, dtype=int), BETA, ETA)
    Q, misses, samples = 7.0, 0, 0
    for _ in range(5000):
        q = cm.q[0]
        scores = np.full(2, -min(q + 1e-9, Q))
        misses += int((scores < -q).sum())
        samples += 2
        cm.update(np.arange(2), scores)
    alpha = miss_target(BETA)
    bound = alpha * samples + (Q - BETA + ETA * 2) / ETA
    assert misses <= bound
    assert misses >= 0.9 * bound - 2  # the bound is nearly reached: it is tight
    assert BETA <= cm.q[0] <= Q + ETA * 2


@pytest.mark.parametrize("scale", [1.0, 3.0])
def test_gaussian_stream_reaches_the_target(scale):
    """Scores N(0, scale^2): calibrated (scale 1) the multiplier stays near beta (the floor
    makes the rate a little lower than the target: after a miss the band is wider for ~1 /
    (eta alpha) samples); three times too narrow it rises to about 3 beta; either way the miss
    rate is within the deterministic bound of the target."""
    rng = np.random.default_rng(0)
    n_steps, per_step = 40_000, 2
    cm = ConformalMultiplier(np.zeros(per_step, dtype=int), BETA, ETA)
    scores = scale * rng.standard_normal((n_steps, per_step))
    misses, samples, q = _stream(cm, scores)
    alpha = miss_target(BETA)
    Q = float(-scores.min())
    assert misses / samples <= alpha + (Q - BETA + ETA * per_step) / (ETA * samples)
    if scale == 1.0:  # a well-specified model is barely widened: on average < 10 %
        assert q[0] <= 1.1 * BETA
        assert misses / samples >= 0.5 * alpha
    else:  # the score's 1 - alpha quantile (7.5), and near the target rate (binomial 5 sd)
        assert q[0] == pytest.approx(scale * BETA, rel=0.1)
        assert misses / samples >= alpha - 5 * math.sqrt(alpha / samples)


def test_drift_is_tracked_within_a_stated_number_of_steps():
    """The model error's scale jumps from 1 to 4 std at step 10,000: within 2,000 steps the
    multiplier is at the new quantile and the miss rate of the rest meets the target."""
    rng = np.random.default_rng(1)
    cm = ConformalMultiplier(np.zeros(1, dtype=int), BETA, ETA)
    first = rng.standard_normal((10_000, 1))
    _stream(cm, first)
    second = 4.0 * rng.standard_normal((30_000, 1))
    _stream(cm, second[:2000])
    assert cm.q[0] > 0.8 * 4.0 * BETA
    misses, samples, _ = _stream(cm, second[2000:])
    assert misses / samples <= 1.5 * miss_target(BETA)


def test_multipliers_are_per_learner():
    cm = ConformalMultiplier(np.array([0, 0, 1, 2]), BETA, ETA)
    cm.update(np.array([1, 3]), np.array([-10.0, 0.0]))
    np.testing.assert_allclose(cm.multiplier(np.arange(4)),
                               [BETA + ETA * (1 - miss_target(BETA))] * 2 + [BETA, BETA])


def test_per_barrier_steps_take_each_learners_largest_and_zero_freezes():
    """Barriers 0, 1 share learner 0 (steps 0 and 1: it takes 1), barrier 2 has step 0: its
    band stays the paper's whatever it misses."""
    cm = ConformalMultiplier(np.array([0, 0, 1]), BETA, [0.0, 1.0, 0.0])
    np.testing.assert_array_equal(cm.step, [1.0, 0.0])
    for _ in range(10):
        cm.update(np.arange(3), np.full(3, -50.0))
    assert cm.q[0] == pytest.approx(BETA + 20 * (1 - miss_target(BETA)))  # 2 per step
    assert cm.q[1] == BETA


def test_controller_takes_per_barrier_steps():
    ctrl = SafetyController(-np.ones(2), np.ones(2), n_barriers=3, calibration="conformal",
                            calibration_step=(0.0, 0.5, 2.0))
    np.testing.assert_array_equal(ctrl.conformal.step, [0.0, 0.5, 2.0])
    with pytest.raises(ValueError, match="calibration must be one mode or 3"):
        SafetyController(-np.ones(2), np.ones(2), n_barriers=3,
                         calibration=("conformal", "off"))
    with pytest.raises(ValueError, match="calibration_step must be one value or 3"):
        SafetyController(-np.ones(2), np.ones(2), n_barriers=3, calibration="conformal",
                         calibration_step=(0.0, 0.5))


def test_one_learner_mixes_the_multiplier_and_the_margin():
    """Learner 0 serves barrier 0 (multiplier) and barrier 1 (margin): the multiplier adapts
    from barrier 0's misses only, the margin from barrier 1's only (in the learner's noise
    std), each band keeps the other's at rest (``beta``, 0), and an "off" barrier of the
    controller (step 0) stays the paper's."""
    alpha = miss_target(BETA)
    cm = ConformalMultiplier(np.array([0, 0]), BETA, 1.0, additive=[False, True])
    std, noise = np.array([0.1, 0.1]), np.array([0.5, 0.5])
    cm.update(np.arange(2), np.array([-10.0, 0.0]), std, noise)  # only the multiplier's miss
    np.testing.assert_allclose(cm.multiplier(np.arange(2)), [BETA + 1 - alpha, BETA])
    np.testing.assert_allclose(cm.margins(np.arange(2)), [0.0, 0.0])
    cm.update(np.arange(2), np.array([0.0, -10.0]), std, noise)  # only the margin's miss
    np.testing.assert_allclose(cm.multiplier(np.arange(2)), [BETA + 1 - 2 * alpha, BETA])
    np.testing.assert_allclose(cm.margins(np.arange(2)), [0.0, 0.5 * (1 - alpha)])
    ctrl = SafetyController(-np.ones(2), np.ones(2), n_barriers=3, calibration_step=2.0,
                            calibration=("off", "conformal", "conformal-additive"))
    np.testing.assert_array_equal(ctrl.conformal.additive, [False, False, True])
    np.testing.assert_array_equal(ctrl.conformal.step, [0.0, 2.0, 2.0])


@pytest.mark.parametrize(("options", "match"), [
    ({"calibration": "bayes"}, "calibration must be one of"),
    ({"calibration": ("off", "bayes")}, "calibration must be one of"),
    ({"calibration": ()}, "calibration must be a mode"),
    ({"calibration": ("off", "conformal"), "beta": 0.0}, "needs beta > 0"),
    ({"calibration": "conformal", "beta": 0.0}, "needs beta > 0"),
    ({"calibration_step": 0.0}, "calibration_step"),
    ({"calibration_step": float("nan")}, "calibration_step"),
    ({"calibration_step": float("inf")}, "calibration_step"),
    ({"calibration_step": (0.5, -1.0)}, r"calibration_step\[1\]"),
])
def test_bad_calibration_options_are_refused(options, match):
    with pytest.raises(ValueError, match=match):
        FilterConfig(**options)


def _terms(rng, k):
    return [BarrierTerms(derivatives=np.array([rng.uniform(0.05, 0.2), rng.normal()]),
                         lf=float(rng.normal()), lg=rng.normal(size=2),
                         xi=rng.normal(size=3)) for _ in range(k)]


@pytest.mark.parametrize("calibration", ["off", "conformal"])
def test_controller_reports_the_band_it_used(calibration):
    """``delta_b_lower`` is mean + bias - multiplier * std at the applied action, and
    ``last_calibration`` counts the eq. 48 samples below it, step by step (checked from the
    public results: FilterResult and observe's z)."""
    rng = np.random.default_rng(3)
    K = 3
    ctrl = SafetyController(-np.ones(2), np.ones(2), n_barriers=K, warmup_samples=20,
                            calibration=calibration, seed=0)
    total_miss = total = total_near = 0
    for _ in range(120):
        before = _terms(rng, K)
        res = ctrl.filter(rng.uniform(-1, 1, 2), before)
        mult = (np.full(K, BETA) if ctrl.conformal is None
                else ctrl.conformal.multiplier(np.arange(K)))
        bias = ctrl.residuals.bias.copy()  # the observer's state before this step's update
        z = ctrl.observe(before, res.u, _terms(rng, K), 0.004)
        if res.warmup:
            assert ctrl.last_calibration is None
            continue
        pred = np.isfinite(res.delta_b_std)
        np.testing.assert_allclose(res.delta_b_lower[pred],
                                   (res.delta_b_mean + bias - mult * res.delta_b_std)[pred],
                                   rtol=1e-12, atol=1e-12)
        assert np.isnan(res.delta_b_lower[~pred]).all()
        c = ctrl.last_calibration
        ok = pred & np.isfinite(z) & (res.delta_b_std > 0)
        assert c.samples == ok.sum()
        assert c.misses == int((z[ok] < res.delta_b_lower[ok]).sum())
        center = (res.delta_b_mean + bias)[ok]
        assert c.within_2std == int((np.abs(z[ok] - center) <= 2 * res.delta_b_std[ok]).sum())
        near = res.margins[ok] < center - res.delta_b_lower[ok]  # within a band-width
        assert c.near_samples == near.sum()
        assert c.near_misses == int((near & (z[ok] < res.delta_b_lower[ok])).sum())
        total_miss, total = total_miss + c.misses, total + c.samples
        total_near += c.near_samples
    assert total > 200 and total_near > 0  # both kinds: the gate test below
    if calibration == "conformal":  # random terms: far from calibrated, the band widened
        assert ctrl.conformal.q.max() > BETA


def test_off_keeps_the_multiplier_and_the_conformal_one_only_widens():
    rng = np.random.default_rng(4)
    ctrl = SafetyController(-np.ones(2), np.ones(2), n_barriers=2, warmup_samples=20,
                            calibration="conformal", seed=1)
    for _ in range(200):
        before = _terms(rng, 2)
        res = ctrl.filter(rng.uniform(-1, 1, 2), before)
        ctrl.observe(before, res.u, _terms(rng, 2), 0.004)
        assert (ctrl.conformal.q >= BETA).all()


def test_the_gate_adapts_only_where_a_miss_could_decide():
    """With ``calibration_gate`` a step's score moves its learner's multiplier only when the
    constraint's margin at the applied action is below the band's width (``mean + bias -
    lower``): q_after - q_before = eta * sum over those rows of (miss - alpha), checked step by
    step from the public results; the rows far from binding leave it alone (and there are
    both kinds in the stream)."""
    rng = np.random.default_rng(5)
    K, eta = 3, 0.5
    ctrl = SafetyController(-np.ones(2), np.ones(2), n_barriers=K, warmup_samples=20,
                            calibration="conformal", calibration_step=eta,
                            calibration_gate=True, seed=0)
    def terms():  # barrier 0 now and then far from binding (a large h), the others near
        out = _terms(rng, K)
        far = np.array([rng.choice([0.1, 20.0]), out[0].derivatives[1]])
        out[0] = BarrierTerms(far, out[0].lf, out[0].lg, out[0].xi)
        return out

    gated = open_ = 0
    for _ in range(150):
        before = terms()
        res = ctrl.filter(rng.uniform(-1, 1, 2), before)
        q0, bias = ctrl.conformal.q.copy(), ctrl.residuals.bias.copy()
        z = ctrl.observe(before, res.u, terms(), 0.004)
        if res.warmup:
            continue
        ok = np.isfinite(res.delta_b_std) & np.isfinite(z) & (res.delta_b_std > 0)
        width = res.delta_b_mean + bias - res.delta_b_lower
        near = ok & (res.margins < width)
        miss = z < res.delta_b_lower
        expected = np.maximum(q0 + eta * np.where(near, miss - ctrl.conformal.target, 0.0),
                              BETA)
        np.testing.assert_allclose(ctrl.conformal.q, expected, rtol=0, atol=1e-12)
        assert ctrl.last_calibration.near_samples == near.sum()  # the gate's subsequence
        gated, open_ = gated + int(near.sum()), open_ + int((ok & ~near).sum())
    assert gated > 20 and open_ > 20
