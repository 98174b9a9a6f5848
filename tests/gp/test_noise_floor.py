"""The hyperparameter fit keeps the noise variance above its data-relative floor
(``hyper.NOISE_MIN`` x the data's weighted mean square; docs/learners.md, "The hyperparameter
fit")."""

import numpy as np
import pytest

from afvsgp_gym.gp import AFVSGP, VSGP
from afvsgp_gym.gp.hyper import noise_box


def _noise_free(n=200, seed=0):
    rng = np.random.default_rng(seed)
    xi = rng.uniform(-2, 2, (n, 3))
    u = rng.uniform(-1, 1, (n, 2))
    z = np.sin(xi[:, 0]) + 0.5 * np.cos(xi[:, 1]) + (1 + 0.3 * xi[:, 2]) * u[:, 0] - u[:, 1]
    return xi, u, z


@pytest.mark.parametrize("cls", [AFVSGP, VSGP])
def test_fitted_noise_respects_the_floor(cls):
    xi, u, z = _noise_free()
    learner = cls(num_inducing=15).fit(xi, u, z)
    weights = None
    if cls is AFVSGP:
        weights = learner.forgetting ** np.arange(len(z) - 1, -1, -1, dtype=float)
    low, _ = noise_box(z, weights)
    assert np.isclose(np.exp(low), 1e-4 * np.average(z * z, weights=weights), rtol=1e-12)
    assert np.log(learner.noise_variance_) >= low - 1e-9

