"""The AFVSGP bank's compiled core (afvsgp_gym.gp._bank) against the bank's numpy methods and
the independent batch posterior, through the bank's public methods (``backend=`` selects the
path): the same learners through window wrapping and inducing-set changes, the rare cases it
hands back to numpy, and bad input.

The tests at the end reach the core itself (its SIMD copies, its argument checks, a swap
forced to an indefinite K_oo, the layout of old pickles, whether the whitened statistics are
carried): no public call selects or observes those.
"""

import copy
import pickle

import numpy as np
import pytest
from gp_batch_formulas import synthetic
from test_afvsgp_bank import K, P, _assert_equals_batch_posterior, _learners, _rows, _streams

import afvsgp_gym
from afvsgp_gym.gp import AFVSGP, ADPKernel, afvsgp_bank
from afvsgp_gym.gp.afvsgp_bank import AFVSGPBank

EPS = np.finfo(np.float64).eps
BUILT = afvsgp_gym.compiled_extensions()["afvsgp_gym.gp._bank"]
needs_core = pytest.mark.skipif(not BUILT, reason="compiled core not built")


def _pair(streams, u, **kw):
    learners = _learners(streams, u, **kw)
    return (AFVSGPBank.from_learners(learners, backend="compiled"),
            AFVSGPBank.from_learners(learners, backend="numpy"))


def _rel(a, b):
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def _assert_same_learners(comp, ref, tol):
    """Equal inducing-set decisions (counts, sizes and points) and statistics ``S``, ``r``
    within ``tol`` relative."""
    for name in ("n_added_", "n_removed_", "n_inducing_", "n_seen_"):
        np.testing.assert_array_equal(getattr(comp, name), getattr(ref, name), err_msg=name)
    for k in range(comp.n_learners):
        for what in ("inducing", "statistics"):
            for a, b in zip(getattr(comp, what)(k), getattr(ref, what)(k), strict=True):
                assert _rel(a, b) <= tol, (what, k)


def _stream_side_by_side(comp, ref, streams, u, steps, every, seed):
    """Stream ``steps`` of ``streams`` into the compiled and numpy banks side by side, with
    equal update masks; every ``every`` steps predict random subsets of learners at random
    points. Returns (worst relative difference of the moments, largest cond(K_oo + S/s2)
    seen)."""
    rng = np.random.default_rng(seed)
    n_learners, dim = comp.n_learners, comp.input_dim
    worst, cond = 0.0, 1.0
    for i in steps:
        xi, z = _rows(streams, i)
        np.testing.assert_array_equal(comp.update(xi, u[i], z), ref.update(xi, u[i], z))
        if i % every == 0:
            rows = np.sort(rng.choice(n_learners, size=rng.integers(1, n_learners + 1),
                                      replace=False))
            xs = rng.normal(size=(len(rows), dim))
            bc, sc = comp.predict_affine(xs, rows)
            br, sr = ref.predict_affine(xs, rows)
            worst = max(worst, _rel(bc, br), _rel(sc, sr))
            cond = max(cond, float(ref.conditioning()[1].max()))
    return worst, cond


@needs_core
@pytest.mark.parametrize("max_candidates", [None, 1])
def test_compiled_equals_numpy_through_inducing_events(max_candidates):
    """Streamed side by side, the compiled and numpy banks make the same inducing-set
    decisions, keep the same statistics and predict the same moments at random points for
    random subsets of learners, to a tolerance from the conditioning of the posterior (the
    same arithmetic in another order: the whitened solves lose at most ~cond(K_oo + S/s2)
    eps, times a small factor for the n-term sums); the compiled bank also equals the batch
    weighted Titsias posterior."""
    n = P + 10 * P
    streams = _streams(n)
    u = streams[0][1]
    comp, ref = _pair(streams, u)
    comp.max_inducing_candidates = ref.max_inducing_candidates = max_candidates
    worst, cond = _stream_side_by_side(comp, ref, streams, u, range(P, n), every=5, seed=4)
    assert comp.n_added_.min() > 20 and comp.n_removed_.min() > 0
    assert 0.0 < worst < 1e3 * cond * EPS, (worst, cond)
    _assert_same_learners(comp, ref, 1e3 * cond * EPS)
    _assert_equals_batch_posterior(comp, streams, u, n, seed=8)


VECTOR_PATH_SHAPES = [(20, 7, 30), (5, 7, 41), (4, 3, 12), (3, 2, 5)]


def _vector_path_learners(b, m, num_inducing):
    """``(streams, u, learners, window)``: three learners with input b, ubar of m + 1 and
    num_inducing points, fitted to the first window samples of their streams."""
    k_learners, window = 3, 60
    n = window + 6 * window
    streams = [synthetic(np.random.default_rng(30 + k), n, b=b, m=m, noise_std=0.05)
               for k in range(k_learners)]
    u = streams[0][1]
    learners = []
    for k, (xi, _, z, _) in enumerate(streams):
        ls = np.sqrt(b) * (1.0 + 0.2 * k) * np.linspace(0.8, 1.4, (m + 1) * b)
        ker = ADPKernel(ls.reshape(m + 1, b), np.linspace(1.0, 0.4, m + 1))
        learners.append(AFVSGP(ker, 0.0025 * (k + 1), num_inducing=num_inducing,
                               window=window, forgetting=0.95, add_threshold=0.05,
                               swap_margin=0.0).fit(xi[:window], u[:window], z[:window], False))
    return streams, u, learners, window


@needs_core
@pytest.mark.parametrize("b, m, num_inducing", VECTOR_PATH_SHAPES)
def test_compiled_equals_numpy_at_the_vector_paths_shapes(b, m, num_inducing):
    """At the shapes that take the core's vector paths (blocks of VL = 8, 4 or 2 outputs, the
    last one overlapping the one before, in groups of four: the Franka's input b = 20, ubar of
    8 and Mp = 30; Mp = 41, a second group; Mp = 12, one overlapping block; Mp = 5, below a
    block of eight; ubar of 8, 4 and 3, kernels summed two at a time and the Gram products of
    8 and 9 columns) the compiled bank makes the numpy methods' inducing-set decisions, keeps
    their statistics and predicts their moments, to the conditioning tolerance above."""
    streams, u, learners, window = _vector_path_learners(b, m, num_inducing)
    comp = AFVSGPBank.from_learners(learners, backend="compiled")
    ref = AFVSGPBank.from_learners(learners, backend="numpy")
    worst, cond = _stream_side_by_side(comp, ref, streams, u, range(window, len(u)), every=3,
                                       seed=b * 100 + num_inducing)
    assert comp.n_added_.min() > 0
    assert 0.0 < worst < 1e3 * cond * EPS, (worst, cond)
    _assert_same_learners(comp, ref, 1e3 * cond * EPS)


@needs_core
def test_compiled_step_hands_skipped_samples_and_huge_inputs_to_numpy():
    """A point so far out that the numpy methods' exponent expansion overflows (they switch
    to the differences, as the core always does) and a NaN sample (one learner skipped: the
    core hands the step to numpy with nothing changed) leave the two banks equal."""
    n = P + 3 * P
    streams = _streams(n)
    u = streams[0][1]
    comp, ref = _pair(streams, u)
    for i in range(P, P + 20):
        xi, z = _rows(streams, i)
        comp.update(xi, u[i], z)
        ref.update(xi, u[i], z)
    xi, z = _rows(streams, P + 20)
    xi[1, 0] = 1e200  # the expansion's x^2 overflows: numpy's direct exponent
    with np.errstate(over="ignore", invalid="ignore"):  # numpy's own warnings on the way
        np.testing.assert_array_equal(comp.update(xi, u[P + 20], z),
                                      ref.update(xi, u[P + 20], z))
    xi, z = _rows(streams, P + 21)
    z[2] = np.nan
    with np.errstate(over="ignore", invalid="ignore"):  # the window holds the huge point
        np.testing.assert_array_equal(comp.update(xi, u[P + 21], z), [True, True, False, True])
        ref.update(xi, u[P + 21], z)
    xs = np.random.default_rng(1).normal(size=(K, 3))
    xs[3] = 1e200  # far out: the prior, from the direct exponent
    with np.errstate(over="ignore", invalid="ignore"):
        for i in range(P + 22, n):
            xi, z = _rows(streams, i)
            comp.update(xi, u[i], z)
            ref.update(xi, u[i], z)
        bc, sc = comp.predict_affine(xs)
        br, sr = ref.predict_affine(xs)
    assert _rel(bc, br) < 1e-9 and _rel(sc, sr) < 1e-9
    np.testing.assert_allclose(sc[3], np.diag(comp.var[3]), rtol=1e-12, atol=0)
    _assert_same_learners(comp, ref, 1e-9)


def test_backend_switch(without_extensions):
    """``backend`` takes "auto", "numpy" or "compiled" (settable later); "compiled" without
    the core is an ImportError naming it, "auto" then runs numpy."""
    xi, u, z, _ = synthetic(np.random.default_rng(0), P, noise_std=0.05)
    learners = _learners([(xi, u, z, None)] * 2, u)
    with pytest.raises(ValueError, match="backend must be one of"):
        AFVSGPBank.from_learners(learners, backend="yes")
    bank = AFVSGPBank.from_learners(learners, backend="numpy")
    assert bank.compiled is False and bank.backend == "numpy"
    bank.backend = "auto"
    assert bank.compiled is BUILT
    without_extensions("bank")
    assert AFVSGPBank.from_learners(learners).compiled is False
    with pytest.raises(ImportError, match=r"afvsgp_gym\.gp\._bank, which was not built"):
        AFVSGPBank.from_learners(learners, backend="compiled")


@needs_core
def test_either_backend_continues_from_the_others_state(without_extensions):
    """Switched back and forth between updates, each backend predicts from the state (and
    the cached posterior factor) the other left, the numpy bank's moments to the
    conditioning tolerance; a bank unpickled where the core is missing runs numpy."""
    streams = _streams(P + 60)
    u = streams[0][1]
    bank = AFVSGPBank.from_learners(_learners(streams, u), backend="compiled")
    ref = AFVSGPBank.from_learners(_learners(streams, u), backend="numpy")
    xs = np.random.default_rng(2).normal(size=(K, 3))
    for i in range(P, P + 60):
        xi, z = _rows(streams, i)
        bank.backend = ("compiled", "numpy")[i % 2]  # the update on one path ...
        bank.update(xi, u[i], z)
        ref.update(xi, u[i], z)
        for backend in ("numpy", "compiled")[:: 1 - 2 * (i % 3 == 0)]:
            bank.backend = backend  # ... predictions on both, in either order
            tol = 1e3 * float(ref.conditioning()[1].max()) * EPS
            for a, b in zip(bank.predict_affine(xs), ref.predict_affine(xs), strict=True):
                assert _rel(a, b) < tol, (i, backend)
    blob = pickle.dumps(bank)
    without_extensions("bank")
    assert pickle.loads(blob).compiled is False


# ------------------------------------------------------------------ the core itself
# No public call reaches these: the choice of SIMD copy, the core's own argument checks (the
# bank always passes good arrays), a swap forced to an indefinite K_oo, the layout of pickles
# written by older versions, and whether the whitened statistics are carried or re-solved.


@needs_core
@pytest.mark.parametrize("b, m, num_inducing", VECTOR_PATH_SHAPES)
def test_every_copy_of_the_hot_loops_gives_the_same_digits(b, m, num_inducing, restore_simd):
    """Each copy of the core's hot loops this CPU runs (AVX-512, AVX2, the baseline: vectors
    of 8, 4 and 2 lanes, so other blocks and other overlaps) streams the same learners through
    the same inducing-set changes to bit-identical statistics and predictions: the copies
    differ in speed, never in a digit."""
    core = afvsgp_bank._core
    copies = core.simd()[1]
    if len(copies) < 2:
        pytest.skip(f"this CPU runs one copy only ({copies})")
    streams, u, learners, window = _vector_path_learners(b, m, num_inducing)
    xs = np.random.default_rng(5).normal(size=(3, b))
    results = {}
    for name in copies:
        assert core.simd(name)[0] == name
        bank = AFVSGPBank.from_learners(learners, backend="compiled")
        out = []
        for i in range(window, len(u)):
            xi, z = _rows(streams, i)
            bank.update(xi, u[i], z)
            # learner 0 at every step (its whitened statistics carried), all now and then
            out.extend(bank.predict_affine(xs[:1], [0]))
            if i % 7 == 0:
                out.extend(bank.predict_affine(xs))
        assert bank.n_added_.min() > 0 and bank.n_removed_.min() > 0
        for k in range(bank.n_learners):
            out.extend([*bank.statistics(k), *bank.inducing(k)])
        results[name] = out
    first = copies[-1]
    for name in copies[:-1]:
        for i, (a, b_) in enumerate(zip(results[name], results[first], strict=True)):
            np.testing.assert_array_equal(a, b_, err_msg=f"{name} vs {first}, output {i}")
    with pytest.raises(ValueError, match="simd: 'sse9' is not one of this CPU's copies"):
        core.simd("sse9")


def _before_first_swap(bank, streams, u, n):
    """``(bank copy, _install's arguments)`` just before the bank's first swap of an inducing
    point (a point dropped for the new one), streaming samples P to n."""
    seen = []
    install = bank._install

    def spy(*args):
        if not seen and args[-1].drop is not None:
            state = copy.deepcopy(bank)
            state.__dict__.pop("_install", None)
            seen.append((state, copy.deepcopy(args)))
        install(*args)

    bank._install = spy
    for i in range(P, n):
        xi, z = _rows(streams, i)
        bank.update(xi, u[i], z)
        if seen:
            break
    del bank._install
    return seen[0]


@needs_core
def test_indefinite_swap_takes_the_jittered_cholesky_on_both_paths():
    """A swap of inducing points that leaves K_oo indefinite (the new pivot just below the
    Schur complement's zero, eqs. 29-30): the core's factorisation refuses it (NOT_PD) and
    the bank takes the jittered Cholesky, with the same inducing set and statistics as the
    numpy path from the same state, and the same predictions."""
    n = P + 10 * P
    streams = _streams(n)
    u = streams[0][1]
    bank = AFVSGPBank.from_learners(_learners(streams, u), backend="compiled")
    state, (k, xi, ub, kss, k_new, cand) = _before_first_swap(bank, streams, u, n)
    m = int(state.n_inducing_[k])
    keep = np.delete(np.arange(m), cand.drop)
    kn = k_new[keep]
    pivot = kn @ np.linalg.solve(state._koo[k][np.ix_(keep, keep)], kn)  # Schur complement 0
    comp, ref = copy.deepcopy(state), copy.deepcopy(state)
    ref.backend = "numpy"
    for b in (comp, ref):
        with pytest.warns(RuntimeWarning, match="needed jitter"):
            b._install(k, xi, ub, pivot * (1 - 1e-6) - state.jitter[k], k_new, cand)
    _assert_same_learners(comp, ref, 0.0)  # the same digits
    xs = np.random.default_rng(6).normal(size=(K, 3))
    tol = 1e3 * float(ref.conditioning()[1].max()) * EPS  # each path predicts its own way
    for a, b in zip(comp.predict_affine(xs), ref.predict_affine(xs), strict=True):
        assert _rel(a, b) < tol
    assert np.linalg.eigvalsh(comp._koo[k, :m, :m]).min() < 0 < np.diag(comp._l_oo[k]).min()


def _state_arrays(bank):
    """The arguments of the core's ``state`` for ``bank``, as the bank passes them."""
    arrays = {name: getattr(bank, attr) for name, attr in afvsgp_bank._CORE_ARRAYS}
    arrays["k_new"], arrays["kss"], arrays["resid"] = bank._step_out
    return bank._dims, arrays, (bank._inv_phi, bank._phi_p, bank._add_floor,
                                bank.swap_margin, bank._refresh_every)


@needs_core
def test_the_core_takes_the_banks_arrays_once_and_checks_them():
    """The core's state holds the bank's arrays (built on first use, again after new arrays
    are allocated, never pickled); a state of wrong sizes, dtypes, layouts or names is
    refused with a ValueError naming the array, before anything is taken."""
    streams = _streams(P + 5)
    u = streams[0][1]
    bank = AFVSGPBank.from_learners(_learners(streams, u), backend="compiled")
    core = afvsgp_bank._core
    state = bank._core_state()
    assert isinstance(state, core.State) and bank._core_state() is state
    assert pickle.loads(pickle.dumps(bank))._cstate is None
    assert copy.deepcopy(bank)._core_state() is not state
    dims, arrays, settings = _state_arrays(bank)
    for name, bad, message in [
            ("ind_xit", arrays["ind_xit"].transpose(0, 2, 1), "ind_xit must be a C-contiguous"),
            ("stats", arrays["stats"][:, :, 1:].copy(), "stats must hold"),
            ("head", arrays["head"].astype(np.int32), "head must be of dtype int64"),
            ("fresh", arrays["fresh"].astype(np.int64), "fresh must be of dtype bool"),
            ("log_var", np.zeros(3), "log_var must hold 12 elements. Got: 3")]:
        with pytest.raises(ValueError, match=message):
            core.state(dims, {**arrays, name: bad}, settings)
    with pytest.raises(ValueError, match="arrays has no stats"):
        core.state(dims, {**{k: v for k, v in arrays.items() if k != "stats"}, "x": None},
                   settings)
    with pytest.raises(ValueError, match="must hold the 32 arrays"):
        core.state(dims, {**arrays, "x": None}, settings)
    with pytest.raises(ValueError, match="dims must be positive"):
        core.state((0, *dims[1:]), arrays, settings)
    with pytest.raises(TypeError):
        core.update(arrays, np.zeros((K, 3)), np.ones(3), np.zeros(K))


@needs_core
def test_compiled_entry_points_refuse_bad_input():
    """Wrong sizes, dtypes and rows give a ValueError naming the argument; a refused call
    writes nothing. (The bank's own refusals, which change nothing either, are tested on the
    default backend in test_afvsgp_bank.py.)"""
    streams = _streams(P + 5)
    u = streams[0][1]
    bank = AFVSGPBank.from_learners(_learners(streams, u), backend="compiled")
    core = afvsgp_bank._core
    dims, arrays, _ = _state_arrays(bank)
    n, c = 2, bank.action_dim + 1
    args = [bank._core_state(), n, np.array([0, 1]), np.zeros((n, 3)), np.empty((n, c)),
            np.empty((n, c, c))]
    assert core.predict(*args) == 0
    for i, bad, message in [(2, np.array([0, K]), "rows"),
                            (3, np.zeros((n, 4)), "xi must hold 6 elements"),
                            (2, np.array([0, 1], dtype=np.int32), "rows must be of dtype int64"),
                            (4, np.empty((n, c))[:, ::-1], "b_out must be a C-contiguous")]:
        with pytest.raises(ValueError, match=message):
            core.predict(*args[:i], bad, *args[i + 1:])
    with pytest.raises(ValueError, match="z must hold 4 elements"):
        core.update(bank._core_state(), np.zeros((K, 3)), np.ones(c), np.zeros(K + 1))
    koo, l_oo, koo_inv, fresh = (arrays[k] for k in ("koo", "l_oo", "koo_inv", "fresh"))
    with pytest.raises(ValueError, match="k and m"):
        core.factor_inverse(dims, K, 3, True, koo, l_oo, koo_inv, fresh)
    with pytest.raises(ValueError, match="koo_inv must be of dtype float64"):
        core.factor_inverse(dims, 0, 3, True, koo, l_oo, koo_inv.astype(np.float32), fresh)
    not_pd = koo.copy()
    not_pd[0, 1, 1] = -1.0
    snap = pickle.dumps(bank)
    assert core.factor_inverse(dims, 0, 3, True, not_pd, l_oo, koo_inv, fresh) == -2  # NOT_PD
    assert pickle.dumps(bank) == snap  # nothing written
    m = int(bank.n_inducing_[0])
    install = (0, m, m, True, 1, 1.0, 1.0, 0.0, 1.0, np.zeros(3), np.ones(c),
               np.zeros(bank.num_inducing), np.zeros(m), np.zeros(1), np.zeros(m))
    with pytest.raises(ValueError, match="pos"):  # a slot out of range
        core.install(bank._core_state(), *install)
    bad = list(install)
    bad[2], bad[12] = 0, np.zeros(m + 1)  # a replace with srow too long
    with pytest.raises(ValueError, match="srow must hold"):
        core.install(bank._core_state(), *bad)
    assert pickle.dumps(bank) == snap


@needs_core
def test_a_bank_pickled_with_inducing_inputs_by_point_loads():
    """A bank pickled when the inducing inputs were stored by point, (K, Mp, b), and without
    the whitened statistics loads with them by dimension and none kept, and predicts and
    updates the same digits as the bank it was."""
    streams = _streams(P + 30)
    u = streams[0][1]
    bank = AFVSGPBank.from_learners(_learners(streams, u), backend="compiled")
    for i in range(P, P + 20):
        xi, z = _rows(streams, i)
        bank.update(xi, u[i], z)
    state = dict(bank.__dict__)  # the older layout, written by hand
    state["_ind_xi"] = np.ascontiguousarray(state.pop("_ind_xit").transpose(0, 2, 1))
    del state["_lsl"], state["_white"]
    old = AFVSGPBank.__new__(AFVSGPBank)
    old.__setstate__(state)
    twin = pickle.loads(pickle.dumps(bank))
    for k in range(K):
        for a, b in zip(old.inducing(k), bank.inducing(k), strict=True):
            np.testing.assert_array_equal(a, b)
    for i in range(P + 20, P + 30):
        xi, z = _rows(streams, i)
        for b in (old, twin):
            b.update(xi, u[i], z)
    xs = np.random.default_rng(3).normal(size=(K, 3))
    for got, want in zip(old.predict_affine(xs), twin.predict_affine(xs), strict=True):
        np.testing.assert_array_equal(got, want)


@needs_core
def test_whitened_statistics_carried_by_the_update_give_the_numpy_moments():
    """A learner predicted at every step has its whitened statistics A = L^-1 S L^-T carried
    by the update (A += scale (l l' - phi^P l_old l_old'), l = L^-1 k_new) through window
    wrapping and inducing-set changes, instead of solved afresh: its moments equal the numpy
    bank's (which solves them) to the conditioning tolerance of the tests above. Whether A was
    carried (``_white``) is read to know that the carried path ran, for long runs of steps."""
    n = P + 12 * P
    streams = _streams(n)
    u = streams[0][1]
    comp, ref = _pair(streams, u, add_threshold=0.9, window=2 * P)  # fills, then wraps
    rng = np.random.default_rng(12)
    worst = 0.0
    carried = longest = 0
    run = np.zeros(2, dtype=int)
    for i in range(P, n):
        xi, z = _rows(streams, i)
        comp.update(xi, u[i], z)
        ref.update(xi, u[i], z)
        # learners 0 and 1 at every step, the others now and then
        rows = np.flatnonzero(np.r_[True, True, rng.random(K - 2) < 0.3])
        kept = comp._white[:2].copy()
        run = np.where(kept, run + 1, 0)
        longest = max(longest, int(run.min()))
        carried += int(kept.sum())
        xs = rng.normal(size=(len(rows), comp.input_dim))
        bc, sc = comp.predict_affine(xs, rows)
        br, sr = ref.predict_affine(xs, rows)
        cond = float(ref.conditioning()[1].max())
        worst = max(worst, _rel(bc, br) / cond, _rel(sc, sr) / cond)
    assert comp.n_added_[:2].min() > 10 and comp.n_removed_[:2].min() > 0
    assert carried > 10 * P and longest >= 10  # A carried over runs of steps, not re-solved
    assert 0.0 < worst < 1e3 * EPS, worst
