"""The transform-form local CSF: the LETKF with a linear sensor, the exact posterior where the
LETKF's linearisation fails, the window sensor, and its input checks."""

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax.filters import local_transform as lt
from csf_jax.filters.letkf import _sparse_local_obs, letkf_analysis, local_obs
from csf_jax.problems.lorenz96 import obs_sites


def _run_both(name, config, x64_dtype=jnp.float64, drop=0.0, steps=15):
    model = csf_jax.problems.get(name, dim=20, num_steps=steps, burn_in=0)
    cfg = csf_jax.problems.config(name, dim=20, num_steps=steps, burn_in=0)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    if drop:
        obs = csf_jax.drop_observations(jax.random.key(5), obs, drop)
    ens = model.initial_ensemble(jax.random.key(1), 12).astype(x64_dtype)
    loc = csf_jax.ring_localization(model.dim, obs_sites(cfg))
    kw = dict(problem=model, key=jax.random.key(2), localization=loc)
    ref = csf_jax.letkf(obs.astype(x64_dtype), ens,
                        config=csf_jax.LETKFConfig(config.radius, config.inflation), **kw)
    got = lt.local_transform_filter(obs.astype(x64_dtype), ens, config=config, **kw)
    return ref, got


@pytest.mark.parametrize("config", [
    lt.LocalTransformConfig(radius=3.0, inflation=1.05),
    lt.LocalTransformConfig(radius=6.0, inflation=1.02, top_iterations=2, iterations=3,
                            reverse_steps=4),
])
def test_linear_sensor_is_the_letkf(x64, config):
    ref, got = _run_both("lorenz96", config, drop=0.2)
    np.testing.assert_allclose(np.asarray(got.mean), np.asarray(ref.mean), rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(got.std), np.asarray(ref.std), rtol=0, atol=1e-10)


def test_every_second_site_is_the_letkf(x64):
    model = csf_jax.problems.get("lorenz96", dim=20, num_steps=8, burn_in=0,
                                    sensor="every", obs_every=2)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 10).astype(jnp.float64)
    loc = csf_jax.ring_localization(20, np.arange(0, 20, 2))
    kw = dict(problem=model, key=jax.random.key(2), localization=loc)
    ref = csf_jax.letkf(obs.astype(jnp.float64), ens, config=csf_jax.LETKFConfig(5.0, 1.03), **kw)
    got = lt.local_transform_filter(obs.astype(jnp.float64), ens,
                                    config=lt.LocalTransformConfig(5.0, 1.03), **kw)
    np.testing.assert_allclose(np.asarray(got.mean), np.asarray(ref.mean), rtol=0, atol=1e-10)


def _site_posteriors(forecast, y, std):
    """Each site's exact posterior mean and std under its own forecast Gaussian and the arctan
    sensor (quadrature): what an analysis that sees one observation per site should give."""
    m, v = np.asarray(forecast.mean(0)), np.asarray(forecast.var(0, ddof=1))
    grid = np.linspace(-15.0, 15.0, 200001)
    means, stds = [], []
    for i in range(forecast.shape[1]):
        logp = -0.5 * (grid - m[i]) ** 2 / v[i] - 0.5 * (y[i] - np.arctan(grid)) ** 2 / std ** 2
        p = np.exp(logp - logp.max())
        p /= p.sum()
        mu = float((p * grid).sum())
        means.append(mu)
        stds.append(float(np.sqrt((p * (grid - mu) ** 2).sum())))
    return np.array(means), np.array(stds)


def test_arctan_analysis_matches_the_exact_posterior_where_the_letkf_does_not(x64):
    """With a radius that reaches only a site's own observation, each site's posterior is 1-d:
    the forecast's Gaussian times the arctan likelihood (std 0.05), known by quadrature. The
    LETKF, linearised at the forecast mean, misses it by up to several posterior stds."""
    d, n = 8, 40
    model = csf_jax.problems.get("lorenz96_arctan", dim=d, num_steps=2, burn_in=0)
    rng = np.random.default_rng(0)
    forecast = jnp.asarray(1.5 + rng.standard_normal((n, d)))
    y = jnp.asarray(np.arctan(1.5 + rng.standard_normal(d)) + 0.05 * rng.standard_normal(d))
    loc = csf_jax.ring_localization(d, np.arange(d))
    table, taper = lt.window_sensor(loc, 0.4)
    post = lt.transform_analysis(forecast, y, model, table, taper,
                                 lt.LocalTransformConfig(radius=0.4, top_iterations=20))
    index, weight = local_obs(loc, 0.4)
    linear = letkf_analysis(forecast, y, model, jnp.asarray(index), weight)
    mean, std = _site_posteriors(forecast, np.asarray(y), 0.05)
    err = np.abs(np.asarray(post.mean(0)) - mean) / std
    assert err.max() < 0.3, err
    assert np.all(np.abs(np.asarray(post.std(0, ddof=1)) / std - 1) < 0.1)
    assert (np.abs(np.asarray(linear.mean(0)) - mean) / std).max() > 2.0


def test_window_observe_reads_each_entry_at_its_own_value():
    """A sensor with two observations of one site and a different function per observation."""
    d = 10
    sites = [3, 3, 7, 0, 9, 5]

    def observe(x):
        return jnp.stack([jnp.arctan(x[3]), x[3] ** 2, jnp.sin(x[7]), 2.0 * x[0], x[9] ** 3,
                          jnp.exp(0.1 * x[5])])

    funcs = [np.arctan, np.square, np.sin, lambda v: 2.0 * v, lambda v: v ** 3,
             lambda v: np.exp(0.1 * v)]
    model = types.SimpleNamespace(observe=observe)
    loc = csf_jax.ring_localization(d, sites)
    table, taper = lt.window_sensor(loc, 2.0)
    values = np.random.default_rng(1).standard_normal((3,) + table.index.shape)
    h, dh = lt.window_observe(model, table, jnp.asarray(values))
    want = np.vectorize(lambda j, v: funcs[j](v))(table.index[None], values)
    np.testing.assert_allclose(np.asarray(h), want, rtol=1e-5, atol=1e-6)
    step = 1e-3
    slope = (np.vectorize(lambda j, v: funcs[j](v))(table.index[None], values + step)
             - np.vectorize(lambda j, v: funcs[j](v))(table.index[None], values - step)) / 2 / step
    np.testing.assert_allclose(np.asarray(dh), slope, rtol=1e-3, atol=1e-3)
    assert table.site.shape == taper.shape


@pytest.mark.parametrize("dim,sites,radius", [(40, range(40), 4.0), (100, range(0, 100, 3), 2.5),
                                              (50, [3, 3, 10, 49, 0, 25], 6.0)])
def test_sparse_local_obs_is_the_dense_one(dim, sites, radius):
    loc = csf_jax.ring_localization(dim, sites)
    index, weight = local_obs.__wrapped__(loc, radius)
    s_index, s_weight = _sparse_local_obs(loc, radius)
    width = s_weight.shape[1]
    assert (weight[:, width:] == 0).all()
    np.testing.assert_array_equal(weight[:, :width], s_weight)
    np.testing.assert_array_equal(np.where(weight[:, :width] > 0, index[:, :width], -1),
                                  np.where(s_weight > 0, s_index, -1))


@pytest.mark.slow
def test_jit_vmap_same_key_and_missing():
    model = csf_jax.problems.get("lorenz96_arctan", dim=20, num_steps=4, burn_in=0)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    obs = obs.at[2, :5].set(jnp.nan)
    ens = model.initial_ensemble(jax.random.key(1), 8)
    loc = csf_jax.ring_localization(20, np.arange(20))

    def run(o, k):
        return lt.local_transform_filter(o, ens, problem=model, key=k, localization=loc,
                                         check_finite=False).mean

    jitted = jax.jit(run)
    a = jitted(obs, jax.random.key(2))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(jitted(obs, jax.random.key(2))))
    assert bool(jnp.isfinite(a).all())
    batch = jax.vmap(run)(jnp.stack([obs, obs]), jnp.stack([jax.random.key(2)] * 2))
    assert batch.shape == (2, 4, 20)
    np.testing.assert_allclose(np.asarray(batch[1]), np.asarray(a), rtol=1e-5, atol=1e-5)


def test_refuses_what_it_cannot_localise():
    model = csf_jax.problems.get("lorenz96", dim=12, num_steps=3, burn_in=0)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 8)
    ring = csf_jax.ring_localization(12, np.arange(12))
    kw = dict(problem=model, key=jax.random.key(2))
    mixing = model._replace(observe=lambda x: x + 0.5 * jnp.roll(x, 1))
    with pytest.raises(ValueError, match="not a point sensor"):
        lt.local_transform_filter(obs, ens, localization=ring, **dict(kw, problem=mixing))
    with pytest.raises(ValueError, match="ring of d=12"):
        lt.local_transform_filter(obs, ens, localization=csf_jax.ring_localization(11, range(12)),
                                  **kw)
    with pytest.raises(ValueError, match="inf"):
        lt.local_transform_filter(obs.at[0, 0].set(jnp.inf), ens, localization=ring, **kw)
    with pytest.raises(ValueError, match="iterations"):
        lt.LocalTransformConfig(iterations=0)
    with pytest.raises(ValueError, match="radius"):
        lt.LocalTransformConfig(radius=0.0)
    with pytest.raises(ValueError, match="t_min"):
        lt.LocalTransformConfig(t_min=1.0)
