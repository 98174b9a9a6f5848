"""Tools of the solver benchmark: the sphere-arm constraints against finite differences of
the simulated barrier (afvsgp_gym.benchmarks.solver), the 40-digit KKT reference against a
closed form and the recorded instances' file format (benchmarks/solver_instances.py)."""

import numpy as np
import pytest
import solver_instances  # benchmarks/solver_instances.py (pytest's pythonpath)

from afvsgp_gym.benchmarks import solver as bench


@pytest.mark.parametrize("n_barriers", [1, 21, 40])
def test_sphere_arm_constraint_is_psi2_by_finite_differences(n_barriers):
    """a0 + a u = h'' + (a1 + a2) h' + a1 a2 h along q(t) = q + t q' + t^2/2 B u."""
    arm = bench.SphereArm.make(n_barriers, seed=4)
    q, qd, o, u_des = arm.sample_states(5, seed=9)
    a1, a2 = bench.ALPHA

    def h(qq, oj):
        p = arm.c + arm.J @ qq
        return (np.linalg.norm(p[None] - oj[:, None], axis=2) - arm.r - arm.R).ravel()

    eps = 1e-4
    for j in range(5):
        u = u_des[j]
        a0, a = arm.constraints(q[j], qd[j], o[j])
        path = [h(q[j] + t * qd[j] + 0.5 * t * t * arm.b * u, o[j]) for t in (-eps, 0.0, eps)]
        hd = (path[2] - path[0]) / (2 * eps)
        hdd = (path[2] - 2 * path[1] + path[0]) / eps**2
        psi2 = hdd + (a1 + a2) * hd + a1 * a2 * path[1]
        np.testing.assert_allclose(a0 + a @ u, psi2, rtol=1e-5, atol=1e-5)


def test_kkt_reference_equals_lorentz_projection():
    """From a guess 1e-8 off (as a clarabel answer), the refinement reaches the closed-form
    projection onto the second-order cone u_1 >= |(u_2, u_3)| (box too large to matter)."""
    m = 3
    low, high = -100 * np.ones(m), 100 * np.ones(m)
    a, a0 = np.array([[1.0, 0.0, 0.0]]), np.array([0.0])
    G = np.zeros((1, m + 1, m + 1))
    G[0, 1, 2] = G[0, 2, 3] = 1.0
    u_nom = np.array([0.2, 1.0, -0.5])
    nx = np.linalg.norm(u_nom[1:])
    want = 0.5 * (u_nom[0] + nx) * np.concatenate([[1.0], u_nom[1:] / nx])
    got = solver_instances.refine_kkt_mp(want + 1e-8, u_nom, a0, a, G, low, high)
    np.testing.assert_allclose(got, want, rtol=1e-15, atol=1e-15)
    # a guess with the wrong active set (the cone inactive there) gives no reference: the
    # refined point violates the constraint
    assert solver_instances.refine_kkt_mp(np.array([50.0, 0.0, 0.0]), u_nom, a0, a, G, low,
                                          high) is None
    # a guess far off with the right active set converges all the same
    far = solver_instances.refine_kkt_mp(np.full(m, 50.0), u_nom, a0, a, G, low, high)
    np.testing.assert_allclose(far, want, rtol=1e-15, atol=1e-15)


def test_recorded_instances_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    m = 7
    inst = []
    for k in (1, 0, 3, 21):
        G = None if k == 3 else rng.normal(size=(k, m + 1, m + 1))
        inst.append((rng.normal(size=m), rng.normal(size=k), rng.normal(size=(k, m)), G))
    path = tmp_path / "inst.npz"
    solver_instances.save_instances(path, inst)
    back = solver_instances.load_instances(path)
    assert len(back) == len(inst)
    for x, y in zip(inst, back, strict=True):
        for u, v in zip(x, y, strict=True):
            if u is None:
                assert v is None
            else:
                np.testing.assert_array_equal(u, v)


def test_generic_programs_are_seeded_feasible_and_active():
    """The generic programs: the same for a seed, Cholesky-shaped cones, the clipped
    proposal violating a cone, and a point of the box satisfying every cone."""
    first = bench.generic_programs(15, 2, seed=3)
    again = bench.generic_programs(15, 2, seed=3)
    for prog, same in zip(first, again, strict=True):
        for x, y in zip(prog, same, strict=True):
            np.testing.assert_array_equal(x, y)
    for u_nom, a0, a, G in first:
        assert u_nom.shape == (bench.M,) and a.shape == (2, bench.M)
        assert np.all(np.tril(G, -1) == 0.0)  # G_i = beta L_i'
        uc = np.clip(u_nom, -1.0, 1.0)
        ubar = np.concatenate([[1.0], uc])
        assert (a0 + a @ uc - np.linalg.norm(G @ ubar, axis=1)).min() < 0.0
        res = bench.SOCPFilter(-np.ones(bench.M), np.ones(bench.M)).solve(u_nom, a0, a, G)
        assert res.feasible and res.status != "inactive"


def test_generic_benchmark_reports_every_program():
    """The generic benchmark's counts per status add up to its programs, and its answers
    agree with clarabel's at clarabel's tolerance (no timing is checked)."""
    out = bench.generic_vs_clarabel(1, 12, seed=5, repeats=1)
    assert sum(v for k, v in out.items() if k.startswith("n_")) == 12
    assert out["max_action_diff"] < 1e-3
    for key in ("filter_median_s", "clarabel_median_s", "ratio_median", "ratio_p90"):
        assert np.isfinite(out[key]) and out[key] > 0.0
