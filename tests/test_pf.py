"""Tests of the bootstrap particle filter: exactness against Kalman, resampling, ESS, API."""

import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax.filters.kalman import kalman_filter
from csf_jax.filters.pf import particle_filter, systematic_resample
from csf_jax.problems.linear import linear_gaussian, to_model


def test_pf_matches_kalman(linear_case):
    """With N = 20000 the PF mean and std are within Monte Carlo error of the Kalman filter.

    Tolerances: the error of a weighted mean is about sigma_post / sqrt(ESS). ESS is ~1e4 on most
    steps (standardised error ~0.01), but when x_0 or an observation is unlikely under the prior it
    drops to a few hundred or, rarely, ~20 (error ~0.2 sigma, carried over a few steps). Over 160
    runs (80 data seeds per case) every run passed the bounds below, the worst reaching 0.099 RMS
    and 0.40 max for the mean (in posterior stds), 0.031 RMS and 0.14 max for the relative std
    error; this seed is typical (~0.01 and 0.03). The std bounds exclude a Kalman filter whose obs
    noise is off by 1.5x (std error >= 0.2 RMS), the mean bounds a filter that ignores the
    observations (mean error >= 0.65 RMS, several stds at worst); both are checked.
    """
    case = linear_case
    pf = particle_filter(case.obs, case.ensemble, model=case.model, key=jax.random.key(1))
    err = case.errors(pf.mean, pf.std)
    assert err.mean_rms < 0.15 and err.mean_max < 0.5, err
    assert err.std_rms < 0.06 and err.std_max < 0.25, err

    prior = case.errors(case.prior_mean)
    assert prior.mean_rms > 0.5, prior
    wrong = kalman_filter(case.obs, model=case.lg._replace(r_std=1.5 * case.lg.r_std))
    assert case.errors(wrong.mean, wrong.std).std_rms > 0.15


def test_pf_result_fields(small_case):
    case = small_case
    K, N, d = case.obs.shape[0], case.ensemble.shape[0], case.ensemble.shape[1]
    pf = particle_filter(case.obs, case.ensemble, model=case.model, key=jax.random.key(0),
                         return_ensembles=True)
    assert pf.mean.shape == pf.std.shape == (K, d)
    assert pf.ensembles.shape == (K, N, d) and pf.ess.shape == (K,)
    assert pf.mean.dtype == jnp.float64
    assert bool(jnp.all((pf.ess >= 1.0) & (pf.ess <= N * (1 + 1e-9))))
    # The resampled ensemble's mean differs from the weighted mean by resampling noise only.
    np.testing.assert_allclose(pf.ensembles.mean(axis=1), pf.mean,
                               atol=4 * float(pf.std.max()) / N**0.5)
    plain = particle_filter(case.obs, case.ensemble, model=case.model, key=jax.random.key(0))
    assert plain.ensembles is None
    np.testing.assert_array_equal(plain.mean, pf.mean)


@pytest.mark.parametrize("seed", range(5))
def test_systematic_resample_counts(x64, seed):
    """Particle j is drawn floor(N w_j) or ceil(N w_j) times; a zero-weight particle never."""
    n = 17
    w = np.random.default_rng(seed).dirichlet(np.ones(n))
    w[3] = 0.0
    w /= w.sum()
    log_w = jnp.log(jnp.asarray(w)) + 5.0  # unnormalised on purpose
    for k in range(20):
        idx = np.asarray(systematic_resample(jax.random.fold_in(jax.random.key(seed), k), log_w))
        assert idx.shape == (n,) and idx.min() >= 0 and idx.max() < n
        counts = np.bincount(idx, minlength=n)
        assert counts[3] == 0
        assert np.all((counts == np.floor(n * w)) | (counts == np.ceil(n * w))), (counts, n * w)


def test_systematic_resample_degenerate():
    """All the weight on one particle: every index is that particle, even in float32."""
    log_w = jnp.full((10,), -jnp.inf).at[7].set(0.0)
    np.testing.assert_array_equal(systematic_resample(jax.random.key(0), log_w), 7)


def _zero_obs_run(r_std, n=1000):
    lg = linear_gaussian(dim=2, obs_dim=2, r_std=r_std, num_steps=10)
    model = to_model(lg)
    ens = model.initial_ensemble(jax.random.key(0), n)
    return particle_filter(jnp.zeros((10, 2)), ens, model=model, key=jax.random.key(1))


def test_ess_flat_likelihood(x64):
    """Obs noise std 1e6: the weights are uniform, so ESS = N at every step."""
    np.testing.assert_allclose(_zero_obs_run(1e6).ess, 1000.0, rtol=1e-6)


def test_ess_peaked_likelihood(x64):
    """Obs noise std 1e-3 against a prior spread ~0.3: a handful of particles carry the weight
    (one, at most steps: the run says so)."""
    with pytest.warns(RuntimeWarning, match="collapsed onto one particle"):
        ess = _zero_obs_run(1e-3).ess
    assert bool(jnp.all(ess < 0.05 * 1000)), ess


def test_pf_vmap_matches_loop(small_case):
    case = small_case
    obs = jnp.stack([case.obs, case.obs + 0.1, case.obs - 0.2])
    ens = jnp.stack([case.ensemble, case.ensemble * 0.9, case.ensemble + 0.5])
    keys = jax.random.split(jax.random.key(3), 3)
    batched = jax.vmap(lambda o, e, k: particle_filter(o, e, model=case.model, key=k))(
        obs, ens, keys)
    for i in range(3):
        single = particle_filter(obs[i], ens[i], model=case.model, key=keys[i])
        for got, want in ((batched.mean[i], single.mean), (batched.std[i], single.std),
                          (batched.ess[i], single.ess)):
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


def test_pf_under_outer_jit(small_case):
    case = small_case
    run = jax.jit(functools.partial(particle_filter, model=case.model, return_ensembles=True))
    jitted = run(case.obs, case.ensemble, key=jax.random.key(5))
    direct = particle_filter(case.obs, case.ensemble, model=case.model, key=jax.random.key(5),
                             return_ensembles=True)
    np.testing.assert_allclose(jitted.mean, direct.mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(jitted.ensembles, direct.ensembles, rtol=1e-9, atol=1e-12)


def test_pf_keys(small_case):
    case = small_case
    run = functools.partial(particle_filter, case.obs, case.ensemble, model=case.model)
    a, b, c = run(key=jax.random.key(7)), run(key=jax.random.key(7)), run(key=jax.random.key(8))
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.ess, b.ess)
    assert not np.allclose(a.mean, c.mean)


def test_pf_float32(linear_obs):
    """Default precision: runs in float32 and tracks the Kalman filter loosely."""
    lg = linear_gaussian(dim=2, obs_dim=2)
    model = to_model(lg)
    obs = jnp.asarray(linear_obs(lg, 0))
    ens = model.initial_ensemble(jax.random.key(1), 2000)
    pf = particle_filter(obs, ens, model=model, key=jax.random.key(2))
    kf = kalman_filter(obs, model=lg)
    assert pf.mean.dtype == jnp.float32
    assert float(jnp.abs((pf.mean - kf.mean) / kf.std).max()) < 0.5


@pytest.mark.parametrize("change, error, match", [
    (lambda o, e: (o[:, :1], e), ValueError, "obs_dim"),
    (lambda o, e: (o, e[:, :1]), ValueError, "dim"),
    (lambda o, e: (o, e[None]), ValueError, r"\(N, d\)"),
    (lambda o, e: (o[None], e), ValueError, r"\(K, m\)"),
    (lambda o, e: (o.at[3, 0].set(-jnp.inf), e), ValueError, "infinite"),
    (lambda o, e: (o, e.at[0, 1].set(jnp.nan)), ValueError, "non-finite"),
    (lambda o, e: (o, e.at[0, 1].set(jnp.inf)), ValueError, "non-finite"),
])
def test_pf_bad_inputs(small_case, change, error, match):
    case = small_case
    obs, ens = change(case.obs, case.ensemble)
    with pytest.raises(error, match=match):
        particle_filter(obs, ens, model=case.model, key=jax.random.key(0))


def test_pf_requires_key(small_case):
    case = small_case
    with pytest.raises(TypeError):
        particle_filter(case.obs, case.ensemble, model=case.model)
    with pytest.raises(TypeError, match="key"):
        particle_filter(case.obs, case.ensemble, model=case.model, key=None)


def _collapsing(n=10):
    """Obs noise std 1e-4 against a prior spread ~1 with 10 particles: one particle takes all."""
    model = to_model(linear_gaussian(dim=2, obs_dim=2, r_std=1e-4, num_steps=3))
    return jnp.ones((3, 2)), model.initial_ensemble(jax.random.key(0), n), model


@pytest.mark.parametrize("route", ["particle_filter", "run"])
def test_a_collapsed_run_warns_once_naming_the_step(route):
    obs, ens, model = _collapsing()
    with pytest.warns(RuntimeWarning, match=r"particle_filter: the particle weights collapsed onto "
                                            r"one particle at step 1 of 3 .*more particles, a "
                                            r"wider likelihood .*another filter") as caught:
        if route == "run":
            result = csf_jax.run(csf_jax.methods.pf(), obs, ens, model=model, key=jax.random.key(1))
        else:
            result = particle_filter(obs, ens, model=model, key=jax.random.key(1))
    assert len([w for w in caught if w.category is RuntimeWarning]) == 1
    assert caught[0].filename == __file__  # points at the caller, not into csf_jax
    assert float(result.ess[0]) < 1.5


def test_no_collapse_warning_for_a_healthy_run_or_under_jit():
    obs, ens, model = _collapsing()
    wide = to_model(linear_gaussian(dim=2, obs_dim=2, r_std=10.0, num_steps=3))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        particle_filter(obs, ens, model=wide, key=jax.random.key(1))
        ess = jax.jit(lambda o, e: particle_filter(o, e, model=model,
                                                   key=jax.random.key(1)).ess)(obs, ens)
    assert float(ess[0]) < 1.5
