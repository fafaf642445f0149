"""Prior scores: the exact Gaussian-mixture score against autodiff of its log-density (float64)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.special import logsumexp

from csf_jax import _linalg, networks
from csf_jax.covariance import estimate as estimate_covariance
from csf_jax.prior import (
    ensemble_moments,
    exact_mixture_prior,
    gaussian_precision,
    gaussian_prior,
    learned_prior,
    mixture_score,
)
from csf_jax.sde import marginal_std


def _mixture_logpdf(x, centers, variance):
    sq = jnp.sum((x - centers) ** 2, axis=-1)
    return logsumexp(-0.5 * sq / variance)


def test_mixture_score_matches_autodiff(x64):
    centers = jax.random.normal(jax.random.key(0), (7, 3)) * 2.0
    x = jax.random.normal(jax.random.key(1), (5, 3)) * 3.0
    for variance in (0.01, 0.5, 50.0):
        expected = jax.vmap(jax.grad(lambda p: _mixture_logpdf(p, centers, variance)))(x)
        np.testing.assert_allclose(mixture_score(x, centers, variance), expected, rtol=1e-9,
                                   atol=1e-9)


def test_single_gaussian_score(x64):
    x = jnp.array([[0.0, 1.0]])
    mu = jnp.array([[2.0, -1.0]])
    np.testing.assert_allclose(mixture_score(x, mu, 4.0), (mu - x) / 4.0, rtol=1e-12)


def test_exact_prior_diffuses_with_process_noise(x64):
    """At time t the components have variance q^2 + sigma_t^2."""
    prior = exact_mixture_prior()
    centers = jnp.array([[1.0], [-1.0]])
    ctx = prior.condition(None, centers, centers + 0.1, 0.3)
    x = jnp.array([[0.2], [3.0]])
    t = 0.25
    var = 0.09 + marginal_std(t) ** 2
    np.testing.assert_allclose(prior.score(None, ctx, x, t), mixture_score(x, centers, var),
                               rtol=1e-12)


def test_gaussian_prior_is_the_diffused_ensemble_gaussian(x64):
    """Score of N(mean, C + sigma_t^2 I) from the ensemble's moments, against autodiff of the
    log-density, at three noise levels."""
    ens = jax.random.normal(jax.random.key(0), (400, 3)) @ jnp.array(
        [[1.0, 0.5, 0.0], [0.0, 0.3, 0.2], [0.0, 0.0, 2.0]]) + jnp.array([1.0, -2.0, 0.5])
    prior = gaussian_prior()
    ctx = prior.condition(None, ens * 0.0, ens, 0.1)
    mean, cov = ens.mean(0), jnp.cov(ens.T)
    np.testing.assert_allclose(ctx.mean, mean, rtol=1e-12)
    np.testing.assert_allclose(ctx.cov, cov, rtol=1e-5, atol=1e-6)  # plus the tiny jitter
    x = jax.random.normal(jax.random.key(1), (5, 3)) * 3.0
    for t in (0.05, 0.4, 1.0):
        total = ctx.cov + marginal_std(t) ** 2 * jnp.eye(3)
        logpdf = lambda p: jax.scipy.stats.multivariate_normal.logpdf(p, mean, total)
        np.testing.assert_allclose(prior.score(None, ctx, x, t), jax.vmap(jax.grad(logpdf))(x),
                                   rtol=1e-8, atol=1e-10)


def test_gaussian_base_network_with_zero_output_is_the_gaussian_prior():
    """``NetworkConfig(base="gaussian")``: the score is the ensemble's Gaussian plus the net's
    correction, so a net whose output layer is zero gives exactly ``gaussian_prior``; the encoder
    sees the first ``encode_particles`` particles, the moments come from all."""
    cfg = networks.NetworkConfig(base="gaussian", hidden=16, heads=2, blocks=1, code_dim=8,
                                 score_hidden=32, score_layers=2)
    params = networks.init_params(jax.random.key(0), cfg, 3)
    out = params["score"]["params"]["out"]
    out["kernel"], out["bias"] = jnp.zeros_like(out["kernel"]), jnp.zeros_like(out["bias"])
    ens = jax.random.normal(jax.random.key(1), (500, 3)) * jnp.array([1.0, 2.0, 0.5]) + 3.0
    learned, gauss = learned_prior(cfg, 64), gaussian_prior()
    ctx = learned.condition(params, None, ens, None)
    np.testing.assert_allclose(ctx.code, networks.encode(params, ens[:64], cfg), rtol=1e-6)
    x = jax.random.normal(jax.random.key(2), (7, 3))
    for t in (0.05, 0.5):
        np.testing.assert_allclose(learned.score(params, ctx, x, t),
                                   gauss.score(None, gauss.condition(None, None, ens, None), x, t),
                                   rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match="base"):
        networks.NetworkConfig(base="mixture")


@pytest.mark.slow  # kept out of the default run's time budget; run with -m slow
def test_gaussian_base_score_takes_one_noise_level_per_row():
    """Training evaluates the Gaussian-base score with one t per target: the same as row by row."""
    cfg = networks.NetworkConfig(base="gaussian", hidden=16, heads=2, blocks=1, code_dim=8,
                                 score_hidden=32, score_layers=2)
    params = networks.init_params(jax.random.key(0), cfg, 3)
    params = jax.tree_util.tree_map(
        lambda a: a + 0.05 * jax.random.normal(jax.random.key(9), a.shape), params)
    prior = learned_prior(cfg)
    ctx = prior.condition(params, None, jax.random.normal(jax.random.key(1), (200, 3)), None)
    x, t = jax.random.normal(jax.random.key(2), (5, 3)), jnp.linspace(0.05, 0.9, 5)
    rows = jnp.stack([prior.score(params, ctx, x[i:i + 1], t[i])[0] for i in range(5)])
    np.testing.assert_allclose(prior.score(params, ctx, x, t), rows, rtol=1e-5, atol=1e-6)


def test_ensemble_moments_of_a_collapsed_ensemble_stay_positive_definite():
    ctx = ensemble_moments(jnp.ones((50, 4)))
    assert np.all(np.linalg.eigvalsh(np.asarray(ctx.cov)) > 0)


def test_learned_prior_encodes_the_noisy_ensemble():
    config = networks.NetworkConfig(hidden=16, heads=2, blocks=1, code_dim=8, score_hidden=16)
    params = networks.init_params(jax.random.key(0), config, dim=2)
    prior = learned_prior(config)
    ens = jax.random.normal(jax.random.key(1), (20, 2))
    code = prior.condition(params, ens * 0.0, ens, 0.1)
    np.testing.assert_allclose(code, networks.encode(params, ens, config), rtol=1e-6)
    s = prior.score(params, code, ens, 0.5)
    assert s.shape == (20, 2) and bool(jnp.isfinite(s).all())


def test_single_ensemble_fit_learns_a_gaussian():
    """fit_unconditional on N(2, 0.5^2) data: the learned score at small noise points to the mean,
    and the training loss falls."""
    from csf_jax.dsm import fit_unconditional
    from csf_jax.prior import unconditional_prior

    config = networks.NetworkConfig(hidden=16, heads=2, blocks=1, code_dim=8, score_hidden=64)
    data = 2.0 + 0.5 * jax.random.normal(jax.random.key(0), (512, 1))
    params0 = networks.init_params(jax.random.key(1), config, dim=1)
    params, losses = fit_unconditional(jax.random.key(2), data, params0, config=config, steps=600)
    assert float(losses[-100:].mean()) < 0.8 * float(losses[:20].mean())
    prior = unconditional_prior(config)
    code = prior.condition(params, None, data, None)
    x = jnp.array([[1.0], [3.0]])
    s = prior.score(params, code, x, 0.05)
    exact = (2.0 - x) / (0.25 + marginal_std(0.05) ** 2)
    assert float(s[0, 0]) > 0 > float(s[1, 0])  # towards the mean from both sides
    np.testing.assert_allclose(s, exact, rtol=0.35)


def _spread_ensemble(seed, n=20, d=40, decay=1e-2):
    """``(n, d)`` float32 of rank n - 1 < d, its variance along singular values decaying from 5 to
    ``5 decay``: the spectrum of a Lorenz-96 ensemble (most of its spread along a few directions)."""
    rng = np.random.default_rng(seed)
    u = np.linalg.qr(rng.standard_normal((n, n)))[0][:, :n - 1]
    v = np.linalg.qr(rng.standard_normal((d, d)))[0][:, :n - 1]
    s = 5.0 * decay ** (np.arange(n - 1) / (n - 2))
    return jnp.asarray(3.0 + (u * s) @ v.T, jnp.float32)


def test_precision_of_a_rank_deficient_float32_ensemble_is_usable():
    """N = 20 < d = 40 in float32: with the floor at 1e-6 of the mean variance alone, 5 of these
    20 ensembles gave a NaN factor or a precision whose ``P^{-1} + I / sigma^2`` was indefinite
    (the guidance's first factorisation, sigma = 9.85); the rounding floor keeps all usable."""
    eye = jnp.eye(40, dtype=jnp.float32)
    usable = jax.jit(lambda ens: jnp.all(jnp.isfinite(
        _linalg.cholesky(gaussian_precision(ens) + eye / 9.85 ** 2))))
    assert [seed for seed in range(20) if not usable(_spread_ensemble(seed))] == []


def test_precision_of_a_full_rank_ensemble_keeps_its_floor():
    """Where the covariance is not singular in the dtype, the rounding floor (here 250 times the
    floor) is not used: the precision is that of ``C + floor I``."""
    ens = jax.random.normal(jax.random.key(0), (200, 10)) * jnp.linspace(0.5, 2.0, 10)

    def with_floor(ens):
        _, cov, floor = estimate_covariance(ens)
        eye = jnp.eye(10, dtype=ens.dtype)
        return _linalg.cho_solve(_linalg.cholesky(cov + floor * eye)[None], eye)

    np.testing.assert_allclose(jax.jit(gaussian_precision)(ens), jax.jit(with_floor)(ens),
                               rtol=1e-5, atol=1e-6)
