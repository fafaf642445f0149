"""Adaptive prior inflation (csf_jax.inflation): zero on consistent data, the closed form at a
surprise, and the filter with it on."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax import CSFConfig, InflationConfig, PriorConfig, SamplerConfig, problems
from csf_jax.inflation import adaptive_inflation, innovation_statistic
from csf_jax.problems.linear import linear_gaussian, to_model

# compared against closed forms (or the PyTorch port) at full float32 precision
pytestmark = pytest.mark.usefixtures("highest_precision")

D = 4
MODEL = to_model(linear_gaussian(D, q_std=0.3, r_std=0.5))  # h = identity, r = 0.25


def _ensemble(key, n=2000, std=1.0):
    return std * jax.random.normal(key, (n, D))


def test_statistic_for_identity_sensor():
    """e^2, v and g by hand: h = I gives g = 1 and v = var + r + base^2."""
    ens = _ensemble(jax.random.key(0))
    y = jnp.full((D,), 2.0)
    e2, v, g = innovation_statistic(ens, y, MODEL, base=0.3)
    np.testing.assert_allclose(g, 1.0, rtol=1e-6)
    np.testing.assert_allclose(e2, (2.0 - ens.mean(0)) ** 2, rtol=1e-5)
    np.testing.assert_allclose(v, ens.var(0) + 0.25 + 0.09, rtol=1e-5)


def test_no_inflation_on_consistent_observations():
    """y drawn from the prior predictive: tau stays at the base in nearly every draw (the trigger
    is a 2-sigma chi-square tail; about 5% false alarms are allowed for)."""
    ens = _ensemble(jax.random.key(1))
    keys = jax.random.split(jax.random.key(2), 200)
    ys = jax.vmap(lambda k: jax.random.normal(k, (D,)) * jnp.sqrt(1.0 + 0.25))(keys)
    taus = jax.vmap(lambda y: adaptive_inflation(ens, y, MODEL, base=0.1))(ys)
    assert float(jnp.mean(taus > 0.1 + 1e-6)) < 0.08
    assert float(jnp.min(taus)) == pytest.approx(0.1, abs=1e-6)


def test_closed_form_at_a_shock():
    """Equal innovations e in every coordinate: sum e^2 / (v + s) = m gives s = e^2 - v."""
    ens = _ensemble(jax.random.key(3), n=20000)
    y = jnp.full((D,), 4.0) + ens.mean(0)
    e2, v, _ = innovation_statistic(ens, y, MODEL)
    tau = adaptive_inflation(ens, y, MODEL)
    expected = np.sqrt(np.mean(16.0 - np.asarray(v)))  # v is nearly equal across coordinates
    assert float(tau) == pytest.approx(expected, rel=2e-2)
    capped = adaptive_inflation(ens, y, MODEL, max_tau=1.0)
    assert float(capped) == pytest.approx(1.0, rel=1e-4)


def test_filter_with_adaptive_inflation_is_deterministic_and_jittable():
    """CSF with the adaptive inflation (exact mixture prior): same key, same result; under jit."""
    model = problems.get("double_well", num_steps=4)
    ens = model.initial_ensemble(jax.random.key(0), 64)
    _, obs = csf_jax.simulate(model, jax.random.key(1))
    cfg = CSFConfig(sampler=SamplerConfig(reverse_steps=5), inflation=InflationConfig(base=0.1, adaptive=True))
    run = lambda o, e, k: csf_jax.filter(None, o, e, model=model, key=k, config=cfg,
                                         check_finite=False).mean
    a = run(obs, ens, jax.random.key(2))
    b = jax.jit(run)(obs, ens, jax.random.key(2))
    assert np.all(np.isfinite(np.asarray(a)))
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


def test_config_checks():
    with pytest.raises(ValueError, match="InflationConfig.max"):
        CSFConfig(inflation=InflationConfig(max=0.0))
    with pytest.raises(ValueError, match="InflationConfig.statistic"):
        CSFConfig(inflation=InflationConfig(statistic="mean"))
    with pytest.raises(ValueError, match="encode_particles"):
        CSFConfig(prior=PriorConfig(encode_particles=1))


def test_median_statistic_ignores_one_outlying_coordinate():
    """One coordinate 6 stds off (a Cauchy-like outlier): the chi-square sum inflates, the median
    form does not; every coordinate off (a shock): both inflate, the median form by the closed
    form ``s = e^2 - v``."""
    ens = _ensemble(jax.random.key(4), n=20000)
    outlier = ens.mean(0).at[0].add(6.0 * np.sqrt(1.25))
    assert float(adaptive_inflation(ens, outlier, MODEL)) > 0.5
    assert float(adaptive_inflation(ens, outlier, MODEL, statistic="median")) == 0.0
    shock = ens.mean(0) + 4.0
    _, v, _ = innovation_statistic(ens, shock, MODEL)
    tau = adaptive_inflation(ens, shock, MODEL, statistic="median")
    assert float(tau) ** 2 == pytest.approx(float(np.median(16.0 - np.asarray(v))), rel=1e-4)
    with pytest.raises(ValueError, match="statistic"):
        adaptive_inflation(ens, shock, MODEL, statistic="mean")


def test_statistics_agree_for_one_observed_coordinate():
    model = to_model(linear_gaussian(1, q_std=0.3, r_std=0.5))
    ens = jax.random.normal(jax.random.key(5), (5000, 1))
    for y in (0.5, 3.0, -5.0):
        a = adaptive_inflation(ens, jnp.array([y]), model, base=0.1)
        b = adaptive_inflation(ens, jnp.array([y]), model, base=0.1, statistic="median")
        assert float(a) == pytest.approx(float(b), rel=1e-3)


def test_entries_the_state_cannot_move_call_for_no_inflation():
    """Stochastic volatility's Gaussian stand-in has mean 0 whatever the state (g = 0): a large
    observation is a large variance, which no inflation of the state explains. The default config
    on that model keeps tau at its base, and filters as the particle filter does (with tau at its
    cap after each large observation it ran off to means of 1e5-1e6)."""
    model = csf_jax.problems.get("stochastic_volatility", num_steps=40)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(100), 500)
    prior_ens = ens + 0.3 * jax.random.normal(jax.random.key(1), ens.shape)
    big = jnp.full((model.obs_dim,), 10.0)
    assert float(adaptive_inflation(prior_ens, big, model, 0.0, 2.0, 10.0,
                                    statistic="median")) == 0.0
    assert float(adaptive_inflation(prior_ens, big, model, 0.0, 2.0, 10.0)) == 0.0
    csf = csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(7))
    pf = csf_jax.particle_filter(obs, ens, model=model, key=jax.random.key(7))
    assert float(csf_jax.rmse(csf.mean, truth[1:])) < 1.2 * float(csf_jax.rmse(pf.mean, truth[1:]))
