"""Parity of the backends "numpy" and "compiled" through the public API: two safety
controllers, one per backend, fed the same inputs give the same answers, to a tolerance from
the conditioning of the learners' posteriors, and the same certified statuses.

The compiled extensions compute the numpy paths' formulas in another order (other rounding),
except the several-cones path of the cone program, which exists only compiled: where several
cones bind, the numpy backend answers by clarabel (``"Solved"``, ``"AlmostSolved"``) what the
compiled one certifies (``"certified:cones"``), to clarabel's accuracy.
"""

import gymnasium as gym
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401  (registers the envs)
from afvsgp_gym import _compiled
from afvsgp_gym.agents import NominalController
from afvsgp_gym.cbf import SafetyController
from afvsgp_gym.types import BarrierSet
from afvsgp_gym.wrappers import SafetyFilter

EPS = np.finfo(np.float64).eps
BACKENDS = ("numpy", "compiled")
needs_all = pytest.mark.skipif(not all(_compiled.available().values()),
                               reason="a compiled extension is not built")
#: clarabel's statuses (the numpy backend's answer where several cones bind)
CLARABEL = ("Solved", "AlmostSolved")
#: relative accuracy of clarabel's answers against the certified ones (its feasibility and gap
#: tolerances, 1e-9, on constraints of order 1e3 and gradients of order 1: a few 1e-6 seen)
CLARABEL_RTOL = 1e-4


def _exact_path(status: str) -> bool:
    """The clipped proposal, or an answer whose KKT conditions were certified: the program's
    unique optimum to rounding (the objective is strictly convex)."""
    return status == "inactive" or status.startswith("certified:")


def _same_decision(a, b):
    """The same warm-up, barriers in the program and feasibility; statuses equal, except that
    two certified answers may name other paths (one cone, or several) and that the numpy
    backend answers by clarabel where the compiled one certifies several cones."""
    assert (a.warmup, a.n_active, a.feasible) == (b.warmup, b.n_active, b.feasible)
    if a.status == b.status or (_exact_path(a.status) and _exact_path(b.status)):
        return
    assert a.status in CLARABEL and b.status.startswith("certified:"), (a.status, b.status)


@needs_all
@pytest.mark.parametrize("r", [1, 2, 3])
def test_known_model_filter_is_the_same_digits_on_either_backend(r):
    """No learner (the known-model QP): the barriers in the program (ties at the activation
    distance, signed zeros) and the answers are the same digits on either backend, and a
    barrier with a non-finite term is flagged alike."""
    rng = np.random.default_rng(r)
    K, m, b = 40, 7, 20
    ctrls = [SafetyController(-np.ones(m), np.ones(m), n_barriers=K, learner="none",
                              activation_distance=0.1, relative_degree=r, backend=backend)
             for backend in BACKENDS]
    for case in range(30):
        bset = BarrierSet(rng.normal(size=(K, r)), rng.normal(size=K), rng.normal(size=(K, m)),
                          rng.normal(size=(K, b)))
        d = bset.derivatives
        d[:5, 0] = [0.1, -0.0, 0.0, 0.1 - 1e-17, np.nextafter(0.1, 1.0)]
        if r > 1:  # h + h'/a_1 at the distance
            d[5, :2] = [0.2, (0.1 - 0.2) * ctrls[0].hocbf.gains[0]]
        if case % 3 == 1:
            getattr(bset, ("derivatives", "xi", "lg")[case % 9 // 3])[7, 0] = np.nan
        u_nom = rng.uniform(-2, 2, m)
        a, c = (ctrl.filter(u_nom, bset) for ctrl in ctrls)
        assert a.status == c.status and a.n_active == c.n_active
        np.testing.assert_array_equal(a.u, c.u)
        np.testing.assert_array_equal(a.margins, c.margins)


def _afvsgp_bank(ctrl):
    """The AFVSGP bank under the controller's bank views (for its conditioning)."""
    bank = ctrl.bank
    while not hasattr(bank, "conditioning"):
        bank = bank.bank
    return bank


@needs_all
@pytest.mark.parametrize("env_id, steps", [("afvsgp_gym/FrankaObstacleStatic-v0", 1500),
                                           ("afvsgp_gym/FrankaObstacleDynamic-v0", 1500)])
def test_whole_arm_filter_agrees_across_backends(env_id, steps):
    """The whole-arm AFVSGP filter (49 barriers, 28 learners) of each backend, fed the same
    terms, proposals and applied actions along one episode (driven by the compiled one's
    answers), through warm-up, the fit and the obstacle's approach:

    - the same warm-up, barriers in the program, feasibility and certified statuses;
    - the learned mean and standard deviation of ``Delta B`` (where both answers are exact)
      within ``1e3 cond eps`` of their size, ``cond`` the largest ``cond(K_oo + S/s2)`` of the
      learners (the whitened solves of either backend lose at most ~``cond eps``, times a
      small factor for the sums, as in tests/gp/test_afvsgp_bank_compiled.py);
    - the actions within that relative change where both are exact (the program's data
      move by no more), within clarabel's accuracy where one came from clarabel.

    What would feed a backend's own rounding back into its state is off: the inducing-set
    decisions (discrete: a near tie decides otherwise; compared in the bank's tests), the
    online exploration (its gate draws noise by a decision), the residual observer (it
    compares the prediction at the controller's own action with the applied one) and the
    conformal margin (a miss is a decision)."""
    opts = dict(learner="afvsgp", seed=0, online_exploration=0.0, residual_correction=0.0,
                learner_kwargs={"adapt_inducing": False}, calibration="off")
    kwargs = {"self_collision": False}  # the 21 pairs and 28 limits of the docstring
    ctrls = [SafetyFilter(gym.make(env_id, **kwargs), backend=backend, **opts).controller
             for backend in BACKENDS]
    env = gym.make(env_id, **kwargs)
    base = env.unwrapped
    policy = NominalController(env)
    obs, _ = env.reset(seed=0)
    cond, counts = 1.0, {"exact": 0, "clarabel": 0, "predicted": 0}
    for t in range(steps):
        terms = base.barrier_terms("nominal")
        u_nom = policy(obs)
        backup = []  # the env's brake is evaluated once per step, for both

        def brake(backup=backup):
            if not backup:
                backup.append(base.backup_action())
            return backup[0].copy()

        a, c = (ctrl.filter(u_nom, terms, None, brake) for ctrl in ctrls)
        _same_decision(a, c)
        scale = 1.0 + np.abs(c.u).max()
        exact = _exact_path(a.status) and _exact_path(c.status)
        predicted = np.isfinite(a.delta_b_mean)
        np.testing.assert_array_equal(predicted, np.isfinite(c.delta_b_mean))
        if predicted.any():
            if t % 50 == 0 or counts["predicted"] == 0:
                cond = max(cond, float(_afvsgp_bank(ctrls[1]).conditioning()[1].max()))
            counts["predicted"] += 1
        tol = 1e3 * cond * EPS
        if exact:
            counts["exact"] += 1
            assert np.abs(a.u - c.u).max() <= tol * scale, t
            if predicted.any():
                size = np.abs(c.delta_b_mean[predicted]) + c.delta_b_std[predicted]
                for x, y in ((a.delta_b_mean, c.delta_b_mean), (a.delta_b_std, c.delta_b_std)):
                    assert np.all(np.abs(x[predicted] - y[predicted]) <= tol * size), t
        else:
            counts["clarabel"] += a.status in CLARABEL
            assert np.abs(a.u - c.u).max() <= CLARABEL_RTOL * scale, (t, a.status, c.status)
        applied = c.u.astype(env.action_space.dtype)
        obs, _, terminated, truncated, _ = env.step(applied)
        after = base.barrier_terms("nominal")
        for ctrl in ctrls:
            ctrl.observe(terms, applied.astype(np.float64), after, float(base.dt))
        assert not (terminated or truncated)
    env.close()
    assert counts["predicted"] > 300 and counts["exact"] > 300 and counts["clarabel"] > 20, counts
