"""The EnKF-N's adaptive inflation of the local filters (``LETKFConfig.adaptive``,
``LocalTransformConfig.adaptive``): what it estimates on draws whose spread is known, and how the
filters take it."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax.filters.letkf import enkf_n_inflation
from csf_jax.problems.linear import linear_gaussian, to_model

M, N = 60, 40
MODEL = to_model(linear_gaussian(M, M, H=np.eye(M), r_std=0.5))


def _case(seed: int, spread: float):
    """A forecast ensemble of ``N(0, I_M)`` with its anomalies scaled by ``spread``, and an
    observation of a truth drawn from ``N(0, I_M)`` through ``H = I``, ``R = 0.5^2 I``."""
    k1, k2, k3 = jax.random.split(jax.random.key(seed), 3)
    ens = jax.random.normal(k1, (N, M))
    ens = ens.mean(0) + spread * (ens - ens.mean(0))
    truth = jax.random.normal(k2, (M,))
    y = truth + 0.5 * jax.random.normal(k3, (M,))
    return ens, y


def _factors(spread: float, certainty: float = 1.0) -> np.ndarray:
    fn = jax.jit(lambda e, y: enkf_n_inflation(e, y, MODEL, certainty))
    return np.array([float(fn(*_case(seed, spread))) for seed in range(20)])


def test_an_ensemble_half_as_wide_as_its_errors_is_widened_about_twofold():
    f = _factors(0.5)
    assert 1.6 < np.median(f) and f.max() <= 2.0, f


def test_a_wider_ensemble_is_widened_less():
    """The EnKF-N's prior expects a finite ensemble to be too narrow, so an ensemble drawn as
    wide as its errors is still widened (about 1.4x here, 60 observations and 40 members), but
    clearly less than one half as wide."""
    assert np.median(_factors(1.0)) < 0.8 * np.median(_factors(0.5))


def test_a_certain_hyperprior_inflates_less():
    assert np.median(_factors(0.5, certainty=50.0)) < np.median(_factors(0.5, certainty=1.0))


def test_no_observed_entry_no_inflation():
    ens, y = _case(0, 0.5)
    assert float(enkf_n_inflation(ens, jnp.full_like(y, jnp.nan), MODEL, 1.0)) == 1.0
    part = y.at[: M // 2].set(jnp.nan)
    assert float(enkf_n_inflation(ens, part, MODEL, 1.0)) > 1.0


@pytest.mark.parametrize("bad", [-1.0, float("inf"), float("nan"), True, "1"])
def test_refuses_a_bad_certainty(bad):
    for cls in (csf_jax.LETKFConfig, csf_jax.LocalTransformConfig):
        with pytest.raises(ValueError, match="adaptive must be a finite number"):
            cls(adaptive=bad)


@pytest.mark.parametrize("name", ["letkf", "local_transform_filter"])
def test_filters_widen_a_collapsed_ensemble(name):
    """On a linear-Gaussian ring observed everywhere, an initial ensemble with a tenth of the
    truth's spread: with the adaptive inflation the first analysis spreads wider than without,
    and the run's error is smaller."""
    d = 20
    lg = linear_gaussian(d, d, H=np.eye(d), r_std=0.5, q_std=0.3)
    model = to_model(lg)
    loc = csf_jax.ring_localization(d, np.arange(d))
    truth, obs = csf_jax.simulate(model, jax.random.key(0), num_steps=30)
    ens = 0.1 * jax.random.normal(jax.random.key(1), (N, d)) + 3.0
    fn = getattr(csf_jax, name)
    base = csf_jax.LETKFConfig() if name == "letkf" else csf_jax.LocalTransformConfig()
    runs = {a: fn(obs, ens, model=model, key=jax.random.key(2), localization=loc,
                  config=dataclasses.replace(base, adaptive=a)) for a in (0.0, 1.0)}
    assert float(runs[1.0].std[0].mean()) > float(runs[0.0].std[0].mean())
    assert csf_jax.rmse(runs[1.0].mean, truth[1:]) < csf_jax.rmse(runs[0.0].mean, truth[1:])
