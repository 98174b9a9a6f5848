"""Learners of the HOCBF model error ``Delta B^(r)``, pluggable by name.

``LEARNERS`` lists the names accepted by :func:`make_learner` and the safety filter:

- ``"none"``: nominal model only (``Delta B = 0``),
- ``"oracle"``: the filter uses the true model terms (upper bound; nothing is learned),
- ``"gp"``: exact GP (``afvsgp_gym.gp.ExactGP``),
- ``"vsgp"``: variational sparse GP (Titsias 2009, ``VSGP``),
- ``"sogp"``: streaming sparse GP (Bui 2017, ``SOGP``),
- ``"afvsgp"``: adaptive forgetting VSGP (paper sec. III, ``AFVSGP``), the default.
"""

from __future__ import annotations

import numpy as np

LEARNERS = ("none", "oracle", "gp", "vsgp", "sogp", "afvsgp")
LEARNING = ("gp", "vsgp", "sogp", "afvsgp")
_CLASSES = {"gp": "ExactGP", "vsgp": "VSGP", "sogp": "SOGP", "afvsgp": "AFVSGP"}


def check_learner_name(name) -> str:
    """Return ``name`` if it is in :data:`LEARNERS`, else raise ``ValueError`` listing them."""
    if not isinstance(name, str) or name not in LEARNERS:
        raise ValueError(f"learner must be one of {list(LEARNERS)}. Got: {name!r}")
    return name


class ZeroLearner:
    """``Delta B = 0`` with zero covariance (learners ``"none"`` and ``"oracle"``)."""

    def __init__(self, action_dim: int):
        self.action_dim = int(action_dim)

    def fit(self, xi, u, z, learn_hyperparameters: bool = True) -> ZeroLearner:
        return self

    def update(self, xi, u, z) -> ZeroLearner:
        return self

    def predict_affine(self, xi) -> tuple[np.ndarray, np.ndarray]:
        n = np.atleast_2d(xi).shape[0]
        d = self.action_dim + 1
        return np.zeros((n, d)), np.zeros((n, d, d))


def make_learner(name: str, action_dim: int, **kwargs):
    """Construct the learner called ``name`` (kwargs go to the GP class constructor)."""
    check_learner_name(name)
    if name in ("none", "oracle"):
        if kwargs:
            raise ValueError(f"learner {name!r} takes no learner_kwargs. Got: {sorted(kwargs)}")
        return ZeroLearner(action_dim)
    from afvsgp_gym import gp

    return getattr(gp, _CLASSES[name])(**kwargs)
