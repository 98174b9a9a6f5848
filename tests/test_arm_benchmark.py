"""The whole-arm timing benchmark records what it says it times (not how fast it is)."""

import numpy as np

from afvsgp_gym.benchmarks.arm import time_config


def test_filter_latency_is_part_of_each_timed_step():
    res = time_config({"safety_spheres": "ee"}, steps=20, seed=0)
    step, filt, learn = res["step"], res["filter"], res["learners"]
    assert len(step) == len(filt) == len(learn) == len(res["n_active"]) >= 15
    assert np.all(filt > 0.0) and np.all(filt < step)
    assert np.all(learn > 0.0) and np.all(learn < step)  # every learner update is inside
    assert res["n_barriers"][0] == 1 + 28 and res["fit_cpu_s"][0] > 0.0  # with joint limits


def test_learner_time_splits_into_update_and_predictions():
    res = time_config({"safety_spheres": "ee"}, steps=20, seed=0)
    upd, pred, learn = res["update"], res["predict"], res["learners"]
    assert np.all(upd > 0.0)  # every learner learns every step
    np.testing.assert_allclose(upd + pred, learn, rtol=1e-12)
    n = res["n_predicted"]
    assert np.all((n >= 0) & (n <= res["n_active"]))  # only barriers in the program
    assert np.all((pred > 0.0) == (n > 0))


def test_env_kwargs_keep_a_list_of_obstacles():
    """The scale benchmark's clutter reaches the env (the "two" shorthand still expands)."""
    from afvsgp_gym.benchmarks.arm import _env_kwargs
    from afvsgp_gym.benchmarks.scale import CLUTTER

    assert _env_kwargs({"obstacles": CLUTTER})["obstacles"] == CLUTTER and len(CLUTTER) == 25
    assert len(_env_kwargs({"obstacles": "two"})["obstacles"]) == 2


def test_primitives_benchmark_builds_the_typed_scenes_it_names():
    """Each count's list has that many primitives, the table first, every type, and the env
    builds one barrier per (arm sphere, primitive) and the 28 limit barriers from it (the
    benchmarks' env options: no self-collision barriers)."""
    from afvsgp_gym.benchmarks.arm import _env_kwargs
    from afvsgp_gym.benchmarks.primitives import COUNTS, configs, ring_primitives
    from afvsgp_gym.envs.franka import FrankaObstacleEnv

    for n in COUNTS:
        obs = ring_primitives(n)
        assert len(obs) == n and obs[0]["type"] == "plane"
    assert {o["type"] for o in ring_primitives(4)} == {"plane", "box", "capsule", "sphere"}
    env = FrankaObstacleEnv("static", **_env_kwargs({"obstacles": ring_primitives(12)}))
    assert env.n_barriers == 21 * 12 + 28
    env.reset(seed=0)
    assert min(env.barrier_terms("true").h[: 21 * 12]) > 0.0  # clear of the ready pose
    env.close()
    assert len(configs()) == 2 * len(COUNTS)


def test_oscbf_scene_is_its_demo_draw_and_clear_at_the_ready_pose(monkeypatch):
    """benchmarks/oscbf_side_by_side.py draws OSCBF's demo's 25 spheres as the demo does
    (numpy's global generator seeded 0: 50 centres, then 50 radii) without touching numpy's
    global state, and our env builds 21 x 26 pair barriers and the 28 limits from them,
    every pair clear at the ready pose (so both filters start from a safe state)."""
    import pathlib
    import sys

    from afvsgp_gym.benchmarks.arm import _env_kwargs
    from afvsgp_gym.envs.franka import FrankaObstacleEnv

    monkeypatch.syspath_prepend(str(pathlib.Path(__file__).parents[1] / "benchmarks"))
    sys.modules.pop("oscbf_side_by_side", None)
    import oscbf_side_by_side as side

    state = np.random.get_state()[1].copy()  # noqa: NPY002
    centres, radii = side.oscbf_clutter()
    np.testing.assert_array_equal(np.random.get_state()[1], state)  # noqa: NPY002
    saved = np.random.get_state()  # noqa: NPY002
    try:
        np.random.seed(0)  # noqa: NPY002  (the demo's own draw, on the global generator)
        want_c = np.random.uniform(  # noqa: NPY002
            low=[0.2, -0.4, 0.1], high=[0.8, 0.4, 0.3], size=(50, 3))
        want_r = np.random.uniform(low=0.01, high=0.1, size=(50,))  # noqa: NPY002
    finally:
        np.random.set_state(saved)  # noqa: NPY002
    np.testing.assert_array_equal(centres, want_c[:25])
    np.testing.assert_array_equal(radii, want_r[:25])
    env = FrankaObstacleEnv("static", **_env_kwargs({"obstacles": side.our_obstacles(centres,
                                                                                   radii)}))
    assert env.n_barriers == 21 * 26 + 28
    env.reset(seed=0)
    assert min(env.barrier_terms("true").h[: 21 * 26]) > 0.0
    env.close()
