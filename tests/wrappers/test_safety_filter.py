"""SafetyFilter on the point-mass env: info keys, action handling, bad input, vector envs."""

import gymnasium as gym
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401  (registers the ids)
from afvsgp_gym.agents import NominalController
from afvsgp_gym.cbf import LEARNERS
from afvsgp_gym.envs.point_mass import PointMassObstacleEnv
from afvsgp_gym.wrappers import SafetyFilter

PM = "afvsgp_gym/PointMassObstacle-v0"
KEYS = (
    "action_proposed",
    "action_applied",
    "filter_active",
    "filter_feasible",
    "delta_b_mean",
    "delta_b_std",
    "delta_b_true",
    "filter_time_s",
    "warmup",
)


def run_episode(env, seed, max_steps=None):
    policy = NominalController(env.unwrapped)
    obs, _ = env.reset(seed=seed)
    hs, infos = [], []
    while True:
        obs, _, term, trunc, info = env.step(policy(obs))
        hs.append(info["h"])
        infos.append(info)
        if term or trunc or (max_steps and len(hs) >= max_steps):
            return np.array(hs), infos


def test_info_keys_and_action_is_copied():
    env = SafetyFilter(gym.make(PM, nominal_model="exact"), learner="none")
    env.reset(seed=0)
    action = np.array([1.0, -0.3], dtype=np.float32)
    before = action.copy()
    _, _, _, _, info = env.step(action)
    np.testing.assert_array_equal(action, before)
    for key in KEYS:
        assert key in info
    assert info["action_applied"].dtype == np.float32
    assert env.action_space.contains(info["action_applied"])
    assert info["action_proposed"] is not action


def test_zero_nominal_none_violates_and_oracle_is_safe():
    h_none, _ = run_episode(SafetyFilter(gym.make(PM), learner="none", backup=None), seed=0)
    h_oracle, infos = run_episode(SafetyFilter(gym.make(PM), learner="oracle"), seed=0)
    assert h_none.min() < 0
    assert h_oracle.min() >= 0
    assert all(i["filter_feasible"] for i in infos)
    assert any(i["filter_active"] for i in infos)


class NaNTermsEnv(PointMassObstacleEnv):
    """The point mass whose barrier terms turn NaN after ``nan_after`` steps (a sensor fault)."""

    def __init__(self, nan_after=5, **kw):
        super().__init__(**kw)
        self.nan_after = nan_after

    def barrier_terms(self, model="nominal"):
        terms = super().barrier_terms(model)
        if self._steps >= self.nan_after:
            terms = type(terms)(terms.derivatives * np.nan, terms.lf, terms.lg, terms.xi * np.nan)
        return terms


@pytest.mark.parametrize("learner", ["none", "oracle"])
def test_nan_barrier_terms_give_flagged_fallback(learner):
    env = SafetyFilter(gym.wrappers.TimeLimit(NaNTermsEnv(), 20), learner=learner)
    _, infos = run_episode(env, seed=0)
    for info in infos[6:]:
        assert not info["filter_feasible"]
        assert np.all(np.isfinite(info["action_applied"]))
        assert env.action_space.contains(info["action_applied"])
    assert env.filter_fallbacks >= 14


def test_nan_action_gives_flagged_fallback():
    env = SafetyFilter(gym.make(PM, nominal_model="exact"), learner="none")
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([np.nan, 0.0], dtype=np.float32))
    assert not info["filter_feasible"]
    assert np.all(np.isfinite(info["action_applied"]))


def test_unknown_learner_lists_valid_names():
    with pytest.raises(ValueError) as exc:
        SafetyFilter(gym.make(PM), learner="ekf")
    for name in LEARNERS:
        assert repr(name) in str(exc.value)


def test_env_without_barrier_terms_is_rejected():
    with pytest.raises(TypeError, match="barrier_terms"):
        SafetyFilter(gym.make("CartPole-v1"))


def test_learning_property_and_constructor_args():
    env = SafetyFilter(gym.make(PM), learner="none", alpha=2.0)
    assert env.learning
    env.learning = False
    assert not env.controller.learning
    assert env._saved_kwargs == {"learner": "none", "backup": "env", "oracle_terms": "true",
                                 "obstacle_estimator": "auto", "estimator_process_std": 0.03,
                                 "alpha": 2.0}
    assert env.controller.config.warmup_samples == 200


def test_make_vec_sync():
    envs = gym.make_vec(
        PM,
        num_envs=2,
        vectorization_mode="sync",
        wrappers=[lambda e: SafetyFilter(e, learner="oracle")],
    )
    obs, _ = envs.reset(seed=0)
    for _ in range(3):
        obs, _, _, _, info = envs.step(envs.action_space.sample())
    assert info["filter_feasible"].shape == (2,)
    assert np.all(np.isfinite(obs))
    envs.close()


def test_env_backup_brakes_on_infeasible_steps():
    """Default backup: the env's brake, applied exactly (cast to the action dtype)."""
    env = SafetyFilter(gym.make(PM), learner="none")
    policy = NominalController(env.unwrapped)
    obs, _ = env.reset(seed=0)
    used = 0
    for _ in range(600):
        brake = env.unwrapped.backup_action().astype(np.float32)
        obs, _, term, trunc, info = env.step(policy(obs))
        if info["filter_status"].startswith("backup:"):
            used += 1
            assert not info["filter_feasible"]
            np.testing.assert_array_equal(info["action_applied"], brake)
        else:
            assert not info["filter_status"].startswith("fallback")
        if term or trunc:
            break
    assert used > 0


def test_backup_none_and_callable():
    env = SafetyFilter(gym.make(PM), learner="none", backup=None)
    _, infos = run_episode(env, seed=0, max_steps=600)
    statuses = {i["filter_status"].split(":")[0] for i in infos}
    assert "fallback" in statuses and "backup" not in statuses
    seen = []

    def backup(obs):
        seen.append(obs)
        return np.zeros(2)

    env = SafetyFilter(gym.make(PM), learner="none", backup=backup)
    _, infos = run_episode(env, seed=0, max_steps=600)
    used = [i for i in infos if i["filter_status"].startswith("backup:")]
    assert used and len(seen) == len(used)
    assert all(np.all(i["action_applied"] == 0) for i in used)
    assert all(o.shape == env.observation_space.shape for o in seen)


def test_bad_backup_is_rejected():
    with pytest.raises(ValueError, match="backup"):
        SafetyFilter(gym.make(PM), learner="none", backup="brake")


def test_bad_oracle_terms_are_rejected_by_name():
    with pytest.raises(ValueError, match="oracle_terms"):
        SafetyFilter(gym.make(PM), learner="oracle", oracle_terms="robust")
    with pytest.raises(ValueError, match="oracle_terms"):
        SafetyFilter(gym.make(PM), learner="none", oracle_terms="true_robust")


def test_robust_oracle_is_the_oracle_where_the_true_terms_are_exact():
    """The point mass's true terms are exact (error bound 0): the robust oracle's episode is
    the oracle's, action for action."""

    def actions(oracle_terms):
        env = SafetyFilter(gym.make(PM, nominal_model="zero"), learner="oracle",
                           oracle_terms=oracle_terms)
        policy = NominalController(env)
        obs, _ = env.reset(seed=2)
        out, active = [], 0
        for _ in range(600):  # past the 300 warm-up steps, when the obstacle comes near
            obs, _, _, _, info = env.step(policy(obs))
            out.append(info["action_applied"])
            active += info["filter_active"]
        return np.array(out), active

    (a, active), (b, _) = actions("true"), actions("true_robust")
    np.testing.assert_array_equal(a, b)
    assert active > 0  # the filter acted: the equality is not vacuous


def test_reset_seed_makes_a_filtered_episode_reproducible():
    """``reset(seed=s)`` seeds the filter's exploration noise too (no ``seed=`` given to the
    wrapper): the same script twice gives identical actions, through warm-up and the online
    exploration after it; another seed gives other actions."""

    def actions(seed):
        env = SafetyFilter(gym.make(PM), learner="afvsgp", warmup_samples=60,
                           learner_kwargs={"num_inducing": 8})
        policy = NominalController(env)
        obs, _ = env.reset(seed=seed)
        out = []
        for _ in range(120):
            obs, _, _, _, info = env.step(policy(obs))
            out.append(info["action_applied"])
        assert not info["warmup"]
        return np.array(out)

    a, b, c = actions(3), actions(3), actions(4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_wrong_action_shape_is_refused_naming_the_action():
    env = SafetyFilter(gym.make("afvsgp_gym/PointMassObstacle-v0"), learner="none")
    env.reset(seed=0)
    n = env.action_space.shape[0]
    with pytest.raises(ValueError, match=r"action must have shape"):
        env.step(np.zeros(n + 1))
    obs, *_ = env.step(np.zeros(n))  # the filter still works after the refusal
    assert np.all(np.isfinite(obs))


def test_env_suggestions_are_defaults_under_the_callers_options():
    """``activation_distance`` and ``learner_defaults`` of the env are used unless the caller
    passes the option; learner settings merge key by key, for the named learner only."""
    def env():
        e = gym.make(PM)
        e.unwrapped.activation_distance = 0.3
        e.unwrapped.learner_defaults = {"afvsgp": {"window": 300, "num_inducing": 12}}
        return e

    f = SafetyFilter(env(), learner="afvsgp")
    assert f.controller.config.activation_distance == 0.3
    assert f.controller.config.learner_kwargs == {"window": 300, "num_inducing": 12}
    assert f.controller.bank._kwargs["window"] == 300  # what the learners are built with
    assert f.controller.bank._kwargs["num_inducing"] == 12
    mine = SafetyFilter(env(), learner="afvsgp", activation_distance=0.2,
                        learner_kwargs={"window": 50})
    assert mine.controller.config.activation_distance == 0.2
    assert mine.controller.config.learner_kwargs == {"window": 50, "num_inducing": 12}
    other = SafetyFilter(env(), learner="sogp")
    assert other.controller.config.learner_kwargs == {}
    with pytest.raises(ValueError, match="learner_kwargs"):  # not a dict: refused by name
        SafetyFilter(env(), learner="afvsgp", learner_kwargs="window=50")


def _learned(env, probes):
    """The learners' affine predictions (eq. 20) of every barrier at the probe features."""
    rows = np.arange(env.unwrapped.n_barriers)
    return [np.concatenate([a.ravel() for a in env.controller.bank.predict_affine(x, rows)])
            for x in probes]


def _steps(env, policy, obs, n):
    for _ in range(n):
        obs, _, _, _, info = env.step(policy(obs))
        assert info["learner_error"] is None
    return obs, info


def test_learning_false_freezes_the_learners_and_true_resumes():
    """``env.learning = False`` (evaluation): the learners' predictions at fixed features do
    not move over 150 steps of new data; set back to True, the next steps change them."""
    env = SafetyFilter(gym.make(PM), learner="afvsgp", warmup_samples=60,
                       learner_kwargs={"num_inducing": 8})
    policy = NominalController(env)
    obs, _ = env.reset(seed=1)
    obs, info = _steps(env, policy, obs, 80)
    assert not info["warmup"]
    probes = [env.unwrapped.barrier_terms("nominal").xi[None]]
    obs, _ = _steps(env, policy, obs, 5)
    probes.append(env.unwrapped.barrier_terms("nominal").xi[None])
    env.learning = False
    frozen = _learned(env, probes)
    obs, _ = _steps(env, policy, obs, 150)
    for a, b in zip(_learned(env, probes), frozen, strict=True):
        np.testing.assert_array_equal(a, b)
    env.learning = True
    obs, _ = _steps(env, policy, obs, 20)
    assert not all(np.array_equal(a, b)
                   for a, b in zip(_learned(env, probes), frozen, strict=True))


def test_learners_persist_across_resets():
    """A reset neither refits nor forgets: after it the filter is past its warm-up at once,
    and predicts what it predicted before the reset; the residual correction restarts."""
    env = SafetyFilter(gym.make(PM), learner="afvsgp", warmup_samples=60,
                       learner_kwargs={"num_inducing": 8})
    policy = NominalController(env)
    obs, _ = env.reset(seed=1)
    obs, info = _steps(env, policy, obs, 80)
    assert not info["warmup"]
    bank = env.controller.bank
    probes = [env.unwrapped.barrier_terms("nominal").xi[None]]
    before = _learned(env, probes)
    obs, _ = env.reset(seed=2)
    assert env.controller.bank is bank and not env.controller.warming_up
    assert np.all(env.controller.residual_bias == 0.0)
    for a, b in zip(_learned(env, probes), before, strict=True):
        np.testing.assert_array_equal(a, b)
    _, _, _, _, info = env.step(policy(obs))
    assert not info["warmup"]  # the second episode starts with the fitted learners


def test_bad_learner_kwargs_are_refused_when_the_filter_is_built():
    """Not at the end of the warm-up (where the error used to be caught and learning silently
    switched off): at construction, naming the key."""
    with pytest.raises(ValueError, match=r"learner_kwargs refused by AFVSGP: num_inducing"):
        SafetyFilter(gym.make(PM), learner="afvsgp", learner_kwargs={"num_inducing": 0})
    with pytest.raises(ValueError, match=r"learner_kwargs .* unexpected keyword .*'windw'"):
        SafetyFilter(gym.make(PM), learner="afvsgp", learner_kwargs={"windw": 50})


def test_a_learner_failure_is_reported_counted_and_warned_once(recwarn):
    """A learner that raises inside the loop: the filter goes on; every such step has
    ``info["learner_error"]`` saying where, the episode counts them (``learner_error_steps``,
    in the records and their summary), and one warning is given, not one per step."""
    from afvsgp_gym.evaluation import run_episode, summarize

    env = SafetyFilter(gym.make(PM), learner="afvsgp", warmup_samples=60,
                       learner_kwargs={"num_inducing": 8})
    policy = NominalController(env)
    obs, _ = env.reset(seed=1)
    _steps(env, policy, obs, 70)
    assert not recwarn.list

    def broken(*args):
        raise np.linalg.LinAlgError("a failed factorisation")

    env.controller.bank.update = broken  # every online update fails from here on
    counts, _ = run_episode(env, policy, seed=2, max_steps=30)
    assert counts["learner_error_steps"] == 30
    assert summarize([counts, counts])["learner_error_steps"] == 60
    assert env.controller.n_update_failures == 30
    assert env.controller.learner_error == ("online update: LinAlgError: a failed "
                                            "factorisation")
    warned = [w for w in recwarn.list if issubclass(w.category, RuntimeWarning)]
    assert len(warned) == 1 and "afvsgp learner failed (online update" in str(warned[0].message)
    env.controller.bank.predict_affine = broken  # a failed prediction: that step is flagged
    obs, _ = env.reset(seed=3)
    for _ in range(100):
        obs, _, _, _, info = env.step(policy(obs))
        if info["filter_n_active"]:
            break
    assert info["learner_error"] == ("prediction: LinAlgError: a failed factorisation; online "
                                     "update: LinAlgError: a failed factorisation")
    assert not info["filter_feasible"] and np.all(np.isfinite(info["action_applied"]))
