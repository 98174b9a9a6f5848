"""The Franka envs' side of the shared learner (issue 45): each obstacle pair's model error is
its projection ``n' J_s`` of the joint-acceleration errors, exactly, and the filter runs on it."""

import gymnasium as gym
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401
from afvsgp_gym.wrappers import SafetyFilter


def _stepped(prior, scenario="Dynamic", seed=3, steps=30):
    env = gym.make(f"afvsgp_gym/FrankaObstacle{scenario}-v0", nominal_model=prior)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        env.step(rng.uniform(-0.3, 0.3, 7))
    return env


@pytest.mark.parametrize("prior", ["kinematic", "perturbed"])
def test_pair_model_error_is_the_projection_of_the_joint_errors(prior):
    """Delta h''_k(u) = W_k @ Delta q''(u) for every pair, any action (the kinematics and the
    obstacle's motion are known, so only the joint accelerations differ), with Delta q''_j read
    off joint j's lower range barrier (h = q_j - q_min: h'' = q''_j); the limit rows are
    their sign on their own joint. The error is ~10 m/s^2: the agreement is to rounding."""
    base = _stepped(prior).unwrapped
    nom, true = base.barrier_terms("nominal"), base.barrier_terms("true")
    P, lim = base.n_obstacle_barriers + base.n_self_collision_barriers, base.joint_limits
    lower = P + np.flatnonzero((np.arange(lim.n_barriers) < 2 * lim.n_joints) & (lim.sign > 0))
    W = nom.projection
    assert W.shape == (base.n_barriers, 7)
    for a in np.random.default_rng(0).uniform(-1, 1, size=(4, 7)):
        err = (true.lf - nom.lf) + (true.lg - nom.lg) @ a
        scale = np.abs(err).max()
        assert scale > 1.0
        np.testing.assert_allclose(err[:P], W[:P] @ err[lower], rtol=0, atol=1e-12 * scale)
        np.testing.assert_array_equal(W[P:] @ err[lower], err[P:])


def test_shared_layout_projects_every_pair_onto_the_seven_joints():
    base = gym.make("afvsgp_gym/FrankaObstacleStatic-v0", nominal_model="kinematic").unwrapped
    lay, P = base.shared_barrier_layout, base.n_obstacle_barriers + base.n_self_collision_barriers
    assert P == 21 + 93  # the obstacle pairs and the self-collision pairs, all projected
    assert lay.n_learners == 7 and lay.projected[:P].all() and not lay.projected[P:].any()
    np.testing.assert_array_equal(lay.learner[P:], base.joint_limits.joint)


@pytest.mark.parametrize(("kwargs", "match"), [({"nominal_model": "zero"}, "zero"),
                                               ({"nominal_model": "kinematic",
                                                 "limit_barriers": False}, "limit_barriers")])
def test_shared_learner_refused_where_nothing_projects(kwargs, match):
    env = gym.make("afvsgp_gym/FrankaObstacleStatic-v0", **kwargs)
    with pytest.raises(ValueError, match=match):
        SafetyFilter(env, learner="afvsgp-shared")


def test_shared_learner_refused_on_an_env_without_a_shared_layout():
    with pytest.raises(ValueError, match="shared_barrier_layout"):
        SafetyFilter(gym.make("afvsgp_gym/PointMassObstacle-v0"), learner="afvsgp-shared")


def test_filtered_steps_predict_the_pairs_through_the_joint_learners():
    """After the warm-up, the pairs in the program get a band (their ``delta_b_lower`` is
    finite) from the seven joint learners alone, every step finds a finite action, and the
    learners never fail."""
    env = SafetyFilter(gym.make("afvsgp_gym/FrankaObstacleStatic-v0",
                                nominal_model="kinematic"), learner="afvsgp-shared", seed=0)
    base = env.unwrapped
    assert env.controller.bank.bank.n_learners == 7
    obs, _ = env.reset(seed=0)
    from afvsgp_gym.agents import NominalController

    policy, P, banded = NominalController(env), base.n_obstacle_barriers, 0
    for _ in range(base.warmup_steps + 200):
        obs, _, term, trunc, info = env.step(policy(obs))
        assert info["learner_error"] is None and np.all(np.isfinite(info["action_applied"]))
        banded += int(np.isfinite(info["delta_b_lower"][:P]).any())
    assert banded > 20
    assert env.controller.n_update_failures == 0


@pytest.mark.parametrize(("env_id", "kwargs", "expected"), [
    # one obstacle without self-collision (21 pairs): the per-pair learners, as fast there
    ("afvsgp_gym/FrankaObstacleStatic-v0", {"nominal_model": "perturbed",
                                            "self_collision": False}, "afvsgp"),
    # with them (the default, 114 pairs) the shared learner
    ("afvsgp_gym/FrankaObstacleStatic-v0", {"nominal_model": "perturbed"}, "afvsgp-shared"),
    # the tabletop's clutter with the robot's own model as the prior: the shared learner
    ("afvsgp_gym/FrankaTabletop-v0", {"nominal_model": "perturbed"}, "afvsgp-shared"),
    ("afvsgp_gym/FrankaShelf-v0", {"nominal_model": "exact"}, "afvsgp-shared"),
    # nothing of the dynamics known, or no kinematics at all: the per-pair learners
    ("afvsgp_gym/FrankaTabletop-v0", {"nominal_model": "kinematic"}, "afvsgp"),
    ("afvsgp_gym/FrankaTabletop-v0", {"nominal_model": "zero"}, "afvsgp"),
    # no joint-limit barriers to hold the seven joint learners
    ("afvsgp_gym/FrankaTabletop-v0", {"nominal_model": "perturbed", "limit_barriers": False},
     "afvsgp"),
    ("afvsgp_gym/PointMassObstacle-v0", {}, "afvsgp"),  # no suggestion: the paper's
])
def test_auto_learner_follows_the_env_suggestion(env_id, kwargs, expected):
    """``SafetyFilter``'s default learner ("auto") is the env's suggestion; the filter runs
    it (a projected bank for the shared learner)."""
    env = SafetyFilter(gym.make(env_id, **kwargs))
    assert env.learner_name == env.controller.learner_name == expected
    base = env.unwrapped
    if hasattr(base, "suggested_learner"):
        assert base.suggested_learner() == expected
        if expected == "afvsgp-shared":
            pairs = base.n_obstacle_barriers + base.n_self_collision_barriers
            assert pairs > base.SHARED_LEARNER_PAIRS
            assert env.controller.bank.layout.projected.any()
    env.close()


def test_unknown_learner_is_refused_naming_auto():
    env = gym.make("afvsgp_gym/PointMassObstacle-v0")
    with pytest.raises(ValueError, match="learner must be 'auto' or one of"):
        SafetyFilter(env, learner="afvsgp-shard")
