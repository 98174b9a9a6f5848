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
    builds one barrier per (arm sphere, primitive) and the 28 limit barriers from it."""
    from afvsgp_gym.benchmarks.primitives import COUNTS, configs, ring_primitives
    from afvsgp_gym.envs.franka import FrankaObstacleEnv

    for n in COUNTS:
        obs = ring_primitives(n)
        assert len(obs) == n and obs[0]["type"] == "plane"
    assert {o["type"] for o in ring_primitives(4)} == {"plane", "box", "capsule", "sphere"}
    env = FrankaObstacleEnv("static", obstacles=ring_primitives(12))
    assert env.n_barriers == 21 * 12 + 28
    env.reset(seed=0)
    assert min(env.barrier_terms("true").h[: 21 * 12]) > 0.0  # clear of the ready pose
    env.close()
    assert len(configs()) == 2 * len(COUNTS)
