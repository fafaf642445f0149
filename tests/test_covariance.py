"""Covariance estimators for small ensembles: closed forms, and their use by the Gaussian prior."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax.covariance import (
    CovarianceConfig,
    estimate,
    gaspari_cohn,
    ledoit_wolf_intensity,
    localisation_taper,
)
from csf_jax.prior import gaussian_precision, gaussian_prior
from csf_jax.sde import marginal_std


def _ensemble(n, d, seed=0):
    a = np.tril(np.random.default_rng(seed + 1).normal(size=(d, d))) + 2 * np.eye(d)
    return np.random.default_rng(seed).normal(size=(n, d)) @ a.T + 1.0


def _ledoit_wolf_numpy(x):
    """Ledoit and Wolf (2004), Lemma 3.2-3.4 and Theorem 3.1, written out with the N outer products."""
    n, d = x.shape
    xc = x - x.mean(0)
    s = xc.T @ xc / n
    mu = np.trace(s) / d
    norm2 = lambda a: np.sum(a * a) / d
    delta2 = norm2(s - mu * np.eye(d))
    beta_bar2 = sum(norm2(np.outer(v, v) - s) for v in xc) / n ** 2
    return min(beta_bar2, delta2) / delta2


def test_ledoit_wolf_intensity_matches_the_formula(x64):
    for n, d in ((20, 10), (50, 20), (400, 5)):
        x = _ensemble(n, d, seed=n)
        got = float(ledoit_wolf_intensity(jnp.asarray(x - x.mean(0))))
        np.testing.assert_allclose(got, _ledoit_wolf_numpy(x), rtol=1e-10)
        assert 0.0 < got < 1.0
    # fewer members than coordinates need more shrinkage than many members
    assert ledoit_wolf_intensity(jnp.asarray(_ensemble(15, 20))) > \
        ledoit_wolf_intensity(jnp.asarray(_ensemble(2000, 20)))


def test_ledoit_wolf_shrinks_towards_the_mean_variance(x64):
    x = jnp.asarray(_ensemble(30, 8))
    mean, cov, _ = estimate(x, CovarianceConfig("ledoit_wolf"))
    sample = np.cov(np.asarray(x).T)
    rho = float(ledoit_wolf_intensity(x - x.mean(0)))
    want = (1 - rho) * sample + rho * np.trace(sample) / 8 * np.eye(8)
    np.testing.assert_allclose(cov, want, rtol=1e-10)
    np.testing.assert_allclose(mean, np.asarray(x).mean(0), rtol=1e-12)
    # with 15 members of a 20-d AR(1) Gaussian the shrunk covariance is closer to the truth
    # (Frobenius, mean over 40 ensembles); measured: 0.57x the sample covariance's error
    i = np.arange(20)
    truth = 0.5 ** np.abs(i[:, None] - i[None, :])
    chol = np.linalg.cholesky(truth)
    errs = np.array([[np.linalg.norm(estimate(jnp.asarray(z @ chol.T), c)[1] - truth)
                      for c in (CovarianceConfig(), CovarianceConfig("ledoit_wolf"))]
                     for z in np.random.default_rng(2).normal(size=(40, 15, 20))])
    assert errs[:, 1].mean() < 0.8 * errs[:, 0].mean()


def test_localised_covariance_is_the_tapered_sample_covariance(x64):
    x = jnp.asarray(_ensemble(25, 12))
    sample = np.cov(np.asarray(x).T)
    _, cov, _ = estimate(x, CovarianceConfig("localised", radius=2.0))
    i = np.arange(12)
    taper = gaspari_cohn(np.abs(i[:, None] - i[None, :]) / 2.0)
    np.testing.assert_allclose(cov, sample * taper, rtol=1e-10)
    assert taper[0, 4] == 0.0 and taper[0, 3] > 0.0      # zero from |i - j| = 2 c on
    _, wide, _ = estimate(x, CovarianceConfig("localised", radius=1e6))
    np.testing.assert_allclose(wide, sample, rtol=1e-6)
    _, narrow, _ = estimate(x, CovarianceConfig("localised", radius=0.4))
    np.testing.assert_allclose(narrow, np.diag(np.diag(sample)), atol=1e-12)
    ring = localisation_taper(12, 2.0, periodic=True)
    assert ring[0, 11] == ring[0, 1] > 0 and localisation_taper(12, 2.0)[0, 11] == 0.0
    # positive semi-definite (Schur product theorem), even with fewer members than coordinates
    _, few, _ = estimate(jnp.asarray(_ensemble(5, 12)), CovarianceConfig("localised", 3.0))
    assert np.linalg.eigvalsh(few).min() > -1e-10


def test_gaussian_prior_uses_the_estimator(x64):
    x = jnp.asarray(_ensemble(30, 6))
    cov_cfg = CovarianceConfig("ledoit_wolf")
    prior = gaussian_prior(25.0, cov_cfg)
    assert prior is gaussian_prior(25.0, cov_cfg)          # cached: one jit cache
    ctx = prior.condition(None, x, x, 0.1)
    mean, cov, floor = estimate(x, cov_cfg)
    pts = jnp.asarray(np.random.default_rng(3).normal(size=(4, 6)))
    sigma = marginal_std(0.3)
    want = -np.linalg.solve(cov + (floor + sigma ** 2) * np.eye(6), (pts - mean).T).T
    np.testing.assert_allclose(prior.score(None, ctx, pts, 0.3), want, rtol=1e-8)


def test_covariance_config_errors():
    with pytest.raises(ValueError, match="estimator"):
        CovarianceConfig("shrunk")
    with pytest.raises(ValueError, match="radius"):
        CovarianceConfig("localised", radius=0.0)
    with pytest.raises(TypeError, match="covariance"):
        csf_jax.CSFConfig(prior=csf_jax.PriorConfig(covariance="ledoit_wolf"))


def test_the_kalman_precision_uses_the_estimator(x64):
    x = jnp.asarray(_ensemble(12, 6))
    cfg = CovarianceConfig("localised", radius=1.0)
    _, cov, floor = estimate(x, cfg)
    want = np.linalg.inv(cov + (0.3 ** 2 + floor) * np.eye(6))
    np.testing.assert_allclose(gaussian_precision(x, 0.3, covariance=cfg), want, rtol=1e-8)


@pytest.mark.slow  # kept out of the default run's time budget; run with -m slow
def test_the_filter_uses_the_configured_covariance(x64):
    """``CSFConfig.covariance`` reaches CSF's sampler: a short filter run with a localised
    covariance differs from the sample one's."""
    cfg = CovarianceConfig("localised", radius=1.0)
    model = csf_jax.problems.get("cubic10_indep", num_steps=3)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 20)
    runs = {name: csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(2),
                                 prior=gaussian_prior(25.0, c),
                                 config=csf_jax.CSFConfig(sampler=csf_jax.SamplerConfig(reverse_steps=4), prior=csf_jax.PriorConfig(covariance=c))).mean
            for name, c in (("sample", CovarianceConfig()), ("localised", cfg))}
    assert np.all(np.isfinite(runs["localised"]))
    assert np.abs(runs["localised"] - runs["sample"]).max() > 1e-3
