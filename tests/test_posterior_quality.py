"""One CSF filter step against the exact posterior (issue: posterior sampling). Default sampler,
inflation 0, N = 1000, d = 10: the quadrature reference of ``experiments.posterior_quality``."""

import dataclasses

import numpy as np
import pytest

from csf_jax import CSFConfig, GuidanceConfig
from experiments import posterior_quality as pq

DEFAULT = CSFConfig(prior_inflation=0.0, adaptive_inflation=False)


def _row(case, config, trials=16):
    return pq.evaluate(case, "test", config.reverse_steps, trials=trials, particles=1000, seed=0,
                       config=config)


def test_exact_posterior_reference_matches_kalman():
    """The quadrature itself, on the linear sensor: mean and std equal the Kalman closed form."""
    case = pq.Case("linear", prior_std=0.7, sensor="linear")
    data = pq.make_data(case, pq.jax.random.key(3), 4, 10)
    exact = pq.exact_posterior(case, data)
    var = 1.0 / (1.0 / case.prior_std ** 2 + 1.0 / case.obs_std ** 2)
    mean = var * (data.centres[:, 0] / case.prior_std ** 2 + data.obs[:, 0] / case.obs_std ** 2)
    np.testing.assert_allclose(exact.mean, mean, atol=1e-6)
    np.testing.assert_allclose(exact.std, np.sqrt(var), rtol=1e-5)


@pytest.mark.parametrize("prior_std", [pytest.param(0.3, marks=pytest.mark.slow), 1.0])
def test_default_sampler_is_close_to_the_exact_posterior_on_the_cubic_sensor(prior_std):
    """The issue's check on 8 of the benchmark's 16 trials (28 s here; measured 0.913 / 0.904 at
    s = 1.0, 1.033 / 0.950 at s = 0.3, error / spread ratios)."""
    row = _row(pq.Case("cubic", prior_std=prior_std), DEFAULT, trials=8)
    assert row["finite"]
    assert row["error_ratio"] <= 1.05, row
    assert 0.85 <= row["spread_ratio"] <= 1.15, row


@pytest.mark.slow  # 14 s; the linear case is also checked against Kalman in test_csf.py
def test_default_sampler_is_exact_for_a_linear_gaussian_step():
    row = _row(pq.Case("linear", prior_std=1.0, sensor="linear"), DEFAULT)
    assert row["error_ratio"] <= 1.01 and abs(row["spread_ratio"] - 1.0) <= 0.02, row
    assert row["bias"] <= 0.06, row


@pytest.mark.slow
def test_clipped_dps_fails_the_same_check():
    """The paper's sampler (clipped DPS) at the default step count: the check above can fail."""
    cfg = dataclasses.replace(DEFAULT, guidance=GuidanceConfig(mode="clipped"))
    row = _row(pq.Case("cubic", prior_std=1.0), cfg, trials=4)
    assert not (row["error_ratio"] <= 1.05 and 0.85 <= row["spread_ratio"] <= 1.15), row
