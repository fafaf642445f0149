"""The local CSF (csf_jax.filters.local_csf) and its sparse prior (csf_jax.local_prior): the
precision operators against their dense form, CG against a dense solve, one step of each sampler
against its closed form (the Gaussian posterior; the square-root transform), the filter against the
Kalman filter on a linear ring model, and its refusals."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax.filters.local_csf import (
    LocalCSFConfig,
    ancestral_sample,
    conjugate_gradient,
    flow_sample,
    local_filter,
)
from csf_jax.local_prior import (
    dense_precision,
    local_statistics,
    precision_blocks,
    precision_diagonal,
    precision_matvec,
    precision_noise,
    ring_predecessors,
)
from csf_jax.problems.linear import linear_gaussian, to_model


def _ring_ensemble(n, d, seed=0, corr=0.7, std=2.0, dtype=np.float64):
    dist = np.abs(np.arange(d)[:, None] - np.arange(d)[None])
    dist = np.minimum(dist, d - dist)
    cov = std ** 2 * corr ** dist
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.standard_normal((n, d)) @ np.linalg.cholesky(cov).T + 1.0, dtype)


def test_predecessors_close_the_ring():
    index, valid = ring_predecessors(10, 2)
    assert valid[0].sum() == 0
    assert sorted(index[3][valid[3]]) == [1, 2]
    assert sorted(index[9][valid[9]]) == [0, 1, 7, 8]      # wraps: 0 and 1 are within 2 of 9
    assert np.all(index[valid] < np.nonzero(valid)[0])
    with pytest.raises(ValueError, match="does not fit"):
        ring_predecessors(4, 2)


def test_precision_operators_match_dense_form():
    with jax.enable_x64(True):
        ens = _ring_ensemble(60, 11)
        stats = local_statistics(ens, 3)
        lam = np.asarray(dense_precision(stats))
        np.testing.assert_allclose(lam, lam.T, atol=1e-12)
        assert np.linalg.eigvalsh(lam).min() > 0
        np.testing.assert_allclose(np.asarray(precision_diagonal(stats)), np.diag(lam), rtol=1e-10)
        v = jnp.asarray(np.random.default_rng(1).standard_normal((3, 11)))
        np.testing.assert_allclose(np.asarray(precision_matvec(stats, v)), np.asarray(v) @ lam,
                                   rtol=1e-10, atol=1e-12)
        draws = precision_noise(stats, jax.random.key(0), (100_000, 11), jnp.float64)
        np.testing.assert_allclose(np.cov(np.asarray(draws).T), lam, atol=0.04 * np.abs(lam).max())


def test_precision_blocks_are_the_diagonal_blocks():
    with jax.enable_x64(True):
        stats = local_statistics(_ring_ensemble(60, 24), 2)
        lam = np.asarray(dense_precision(stats))
        blocks = np.asarray(precision_blocks(stats, 6))
        for j in range(4):
            np.testing.assert_allclose(blocks[j], lam[6 * j:6 * j + 6, 6 * j:6 * j + 6],
                                       atol=1e-12)


def test_full_neighbourhood_recovers_the_sample_covariance():
    """With every j < i a predecessor and no regularisation, the regressions are the modified
    Cholesky factorisation of the sample covariance: Lambda^{-1} = C up to the residual variances'
    degrees of freedom (N - 1 - P_i instead of N - 1), undone here."""
    with jax.enable_x64(True):
        n, d = 200, 9
        ens = _ring_ensemble(n, d)
        stats = local_statistics(ens, 4, ridge=0.0, floor=1e-12)
        _, valid = ring_predecessors(d, 4)
        dof = (n - 1 - valid.sum(1)) / (n - 1)
        lam = np.asarray(dense_precision(stats._replace(dinv=stats.dinv / dof)))
        np.testing.assert_allclose(np.linalg.inv(lam), np.cov(np.asarray(ens).T), rtol=1e-8,
                                   atol=1e-10)


def test_conjugate_gradient_solves_spd_systems():
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        m = rng.standard_normal((8, 8))
        a = jnp.asarray(m @ m.T + 8 * np.eye(8))
        rhs = jnp.asarray(rng.standard_normal((4, 8)))
        x = conjugate_gradient(lambda v: v @ a, rhs, jnp.zeros_like(rhs),
                               lambda r: r / jnp.diag(a), 20)
        np.testing.assert_allclose(np.asarray(x), np.linalg.solve(np.asarray(a), np.asarray(rhs).T).T,
                                   rtol=1e-9, atol=1e-10)


def _identity_model(d, r_std=1.0, k=5):
    lg = linear_gaussian(d, q_std=0.5, r_std=r_std, num_steps=k, A=_ring_dynamics(d))
    return lg, to_model(lg)


def _ring_dynamics(d):
    a = 0.6 * np.eye(d) + 0.2 * (np.roll(np.eye(d), 1, 1) + np.roll(np.eye(d), -1, 1))
    return 0.95 * a


def _posterior_case(d=16, b=3, std=2.0):
    _, model = _identity_model(d)
    prior = _ring_ensemble(40, d, std=std)
    stats = local_statistics(prior, b)
    y = jnp.asarray(np.random.default_rng(3).standard_normal(d))
    lam = np.asarray(dense_precision(stats))
    r_inv = 1.0 / model.obs_noise.gaussian_std ** 2
    cov = np.linalg.inv(lam + r_inv * np.eye(d))
    mean = cov @ (lam @ np.asarray(stats.mean) + r_inv * np.asarray(y))
    return model, prior, stats, y, lam, cov, mean


def _sqrtm(m, power):
    w, v = np.linalg.eigh(m)
    return (v * w ** power) @ v.T


@pytest.mark.slow  # default-run budget
def test_ancestral_step_draws_the_gaussian_posterior():
    """The ancestral sampler draws N(A^{-1} r, A^{-1}) at every level: its output is the Gaussian
    posterior of the GMRF prior and the linear sensor, whatever L."""
    with jax.enable_x64(True):
        d = 16
        model, prior, stats, y, _, cov, mean = _posterior_case(d)
        config = LocalCSFConfig(half_width=3, block=8, reverse_steps=5, cg_iterations=40,
                                t_min=1e-3, sampler="ancestral")
        draws = jax.vmap(lambda k: ancestral_sample(model, y, prior, stats, k, config,
                                                    jnp.arange(d)))(
            jax.random.split(jax.random.key(0), 500)).reshape(-1, d)
        se = np.sqrt(np.diag(cov) / draws.shape[0])
        assert np.all(np.abs(np.asarray(draws.mean(0)) - mean) < 5 * se)
        np.testing.assert_allclose(np.cov(np.asarray(draws).T), cov, atol=0.05 * np.diag(cov).max())


@pytest.mark.slow  # default-run budget (about 10 s; the suite is near its 10-minute limit)
def test_flow_step_is_the_square_root_transform():
    """Up the prior's probability-flow ODE and down the posterior's: for a Gaussian prior and a
    linear sensor, ``m_a + P_a^{1/2} Lambda^{1/2} (x - m)`` member by member (up to the top
    level's O(C / sigma^2) and the ODE steps)."""
    with jax.enable_x64(True):
        d = 16
        model, prior, stats, y, lam, cov, mean = _posterior_case(d, std=0.5)
        exact = mean + (np.asarray(prior) - np.asarray(stats.mean)) @ (
            _sqrtm(cov, 0.5) @ _sqrtm(lam, 0.5)).T
        config = LocalCSFConfig(half_width=3, block=8, reverse_steps=30, cg_iterations=40,
                                t_min=1e-7)
        out = np.asarray(flow_sample(model, y, prior, stats, config, jnp.arange(d)))
        assert np.abs(out - exact).max() < 0.01 * np.abs(exact - mean).max()
        coarse = np.asarray(flow_sample(model, y, prior, stats,
                                        dataclasses.replace(config, reverse_steps=3), jnp.arange(d)))
        assert np.abs(coarse - exact).max() > 0.05 * np.abs(exact - mean).max()   # can fail


@pytest.mark.slow  # default-run budget
@pytest.mark.parametrize("sampler", ["flow", "ancestral"])
def test_filter_is_near_kalman_on_a_linear_ring(sampler):
    d, runs = 16, 4
    lg, model = _identity_model(d, k=60)
    truth, obs = jax.vmap(lambda k: csf_jax.simulate(model, k))(
        jax.random.split(jax.random.key(0), runs))
    ens = jax.vmap(lambda k: model.initial_ensemble(k, 100))(
        jax.random.split(jax.random.key(1), runs))
    loc = csf_jax.ring_localization(d, np.arange(d))
    config = LocalCSFConfig(half_width=3, block=8, inflation=1.0, sampler=sampler)
    result = jax.vmap(lambda o, e, k: local_filter(o, e, model=model, key=k, localization=loc,
                                                   config=config, check_finite=False))(
        obs, ens, jax.random.split(jax.random.key(2), runs))
    kalman = jax.vmap(lambda o: csf_jax.kalman_filter(o, model=lg))(obs)
    err = float(jnp.sqrt(jnp.mean((result.mean - truth[:, 1:]) ** 2)))
    best = float(jnp.sqrt(jnp.mean((kalman.mean - truth[:, 1:]) ** 2)))
    assert err < 1.1 * best, (err, best)
    assert bool(result.finite.all())


@pytest.mark.slow  # about a minute of compilation; docs/lorenz96_csf.md runs the same filter
def test_lorenz96_smoke_same_key_and_missing():
    model = csf_jax.problems.get("lorenz96", num_steps=40, burn_in=0)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    obs = csf_jax.drop_observations(jax.random.key(5), obs, 0.2)
    ens = model.initial_ensemble(jax.random.key(1), 40)
    loc = csf_jax.ring_localization(40, np.arange(40))
    run = jax.jit(lambda k: local_filter(obs, ens, model=model, key=k, localization=loc,
                                         check_finite=False))
    a, b = run(jax.random.key(2)), run(jax.random.key(2))
    np.testing.assert_array_equal(np.asarray(a.mean), np.asarray(b.mean))
    err = float(jnp.sqrt(jnp.mean((a.mean[20:] - truth[21:]) ** 2)))
    assert bool(a.finite.all()) and err < 1.0, err       # climatology is 3.6


def test_refuses_what_it_cannot_localise():
    model = csf_jax.problems.get("lorenz96", dim=12, num_steps=3, burn_in=0)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 8)
    ring = csf_jax.ring_localization(12, np.arange(12))
    kw = dict(model=model, key=jax.random.key(2), config=LocalCSFConfig(half_width=2, block=6))
    assert local_filter(obs, ens, localization=ring, **kw).mean.shape == (3, 12)
    with pytest.raises(ValueError, match="ring of d=12"):
        local_filter(obs, ens, localization=csf_jax.ring_localization(11, np.arange(12)), **kw)
    with pytest.raises(ValueError, match="integer sites"):
        local_filter(obs, ens, localization=ring._replace(obs=tuple(float(i) + 0.5
                                                                    for i in range(12))), **kw)
    mixing = model._replace(observe=lambda x: x + 0.5 * jnp.roll(x, 1))
    with pytest.raises(ValueError, match="not a point sensor"):
        local_filter(obs, ens, localization=ring, **dict(kw, model=mixing))
    with pytest.raises(ValueError, match="wider than the ring"):
        local_filter(obs, ens, localization=ring,
                     **dict(kw, config=LocalCSFConfig(half_width=6, block=13)))
    with pytest.raises(ValueError, match="multiple of 2 x block"):
        local_filter(obs, ens, localization=ring,
                     **dict(kw, config=LocalCSFConfig(half_width=2, block=5)))
    with pytest.raises(ValueError, match="inf"):
        local_filter(obs.at[0, 0].set(jnp.inf), ens, localization=ring, **kw)
    with pytest.raises(ValueError, match="half_width"):
        LocalCSFConfig(half_width=0)
    with pytest.raises(ValueError, match="must exceed"):
        LocalCSFConfig(half_width=8, block=16)
    with pytest.raises(ValueError, match="sampler"):
        LocalCSFConfig(sampler="euler")
    with pytest.raises(ValueError, match="inflation"):
        LocalCSFConfig(inflation=0.0)
