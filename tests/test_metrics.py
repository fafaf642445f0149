"""Metrics against closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from csf_jax.metrics import rmse, rmse_over_time, rmse_per_dim, wasserstein_1d


def test_rmse_is_the_paper_formula():
    est = jnp.zeros((2, 3, 2))
    truth = jnp.array([[[3.0, 4.0]] * 3, [[0.0, 0.0]] * 3])  # ||err|| = 5 for run 0, 0 for run 1
    assert float(rmse(est, truth)) == pytest.approx(np.sqrt(25 / 2))
    assert float(rmse_per_dim(est, truth)) == pytest.approx(np.sqrt(25 / 4))
    np.testing.assert_allclose(rmse_over_time(est, truth), np.sqrt(25 / 2) * np.ones(3), rtol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        rmse(est, truth[:, :2])


def test_wasserstein_of_a_shift_is_the_shift():
    a = jax.random.normal(jax.random.key(0), (5000, 2))
    np.testing.assert_allclose(wasserstein_1d(a, a + jnp.array([0.5, -2.0])), [0.5, 2.0],
                               rtol=1e-4)
    assert float(wasserstein_1d(a, a)[0]) == pytest.approx(0.0, abs=1e-7)
