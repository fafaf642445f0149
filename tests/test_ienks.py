"""The local iterative smoother (lag 1): the LETKF where the model is the identity, the ensemble
Kalman update of the propagated ensemble with a linear model, nearer the exact posterior than the
LETKF after a nonlinear step, missing steps, and its input checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax.filters.ienks import smoother_analysis
from csf_jax.filters.letkf import letkf_analysis, local_obs
from csf_jax.problems.linear import LinearGaussian, to_model


def _scalar_model(drift, r_std=0.5):
    """d = m = 1: ``x_{k+1} = drift(x_k)`` (perfect), ``y = x + N(0, r_std^2)``."""
    lg = LinearGaussian(np.eye(1), np.eye(1), 0.0, r_std, np.zeros(1), 1.0, 1, "scalar")
    return to_model(lg)._replace(drift=drift)


def test_identity_model_first_iteration_is_the_letkf(x64):
    model = csf_jax.problems.get("lorenz96", dim=20, num_steps=6, burn_in=0)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    obs = csf_jax.drop_observations(jax.random.key(5), obs, 0.2)
    model = model._replace(drift=lambda x: x, name="lorenz96 identity")
    ens = model.initial_ensemble(jax.random.key(1), 12).astype(jnp.float64)
    loc = csf_jax.ring_localization(20, range(20))
    kw = dict(model=model, key=jax.random.key(2), localization=loc)
    ref = csf_jax.letkf(obs.astype(jnp.float64), ens, config=csf_jax.LETKFConfig(3.0, 1.04), **kw)
    got = csf_jax.ienks(obs.astype(jnp.float64), ens,
                        config=csf_jax.IEnKSConfig(3.0, 1.04, iterations=1), **kw)
    np.testing.assert_allclose(np.asarray(got.mean), np.asarray(ref.mean), rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(got.std), np.asarray(ref.std), rtol=0, atol=1e-10)
    assert np.all(np.asarray(got.info["iterations"]) == 1)


def test_linear_model_one_site_is_the_kalman_update(x64):
    a, r = 0.8, 0.5
    model = _scalar_model(lambda x: a * x, r)
    ens = jax.random.normal(jax.random.key(3), (30, 1), jnp.float64) + 1.0
    y = jnp.asarray([0.3], jnp.float64)
    index, weight = local_obs(csf_jax.ring_localization(1, [0]), 2.0)
    f = np.asarray(a * ens[:, 0])
    p = f.var(ddof=1)
    gain = p / (p + r**2)
    for tol, iterations in ((1.0, 10), (0.0, 4)):      # further iterations stay at the update
        post, count = smoother_analysis(ens, y, model, index, weight, [0], jnp.asarray(1.0),
                                        iterations=iterations, tol=tol)
        assert float(post.mean()) == pytest.approx(f.mean() + gain * (0.3 - f.mean()), abs=1e-10)
        assert float(post[:, 0].var(ddof=1)) == pytest.approx((1 - gain) * p, abs=1e-10)
    assert int(count) == 4


def _exact_posterior_mean(drift, mean, std, y, r):
    """``E[drift(x) | y]`` for ``x ~ N(mean, std^2)``, ``y = drift(x) + N(0, r^2)``: quadrature."""
    x = np.linspace(mean - 8 * std, mean + 8 * std, 20001)
    fx = drift(x)
    logw = -0.5 * ((x - mean) / std) ** 2 - 0.5 * ((y - fx) / r) ** 2
    w = np.exp(logw - logw.max())
    return float((w * fx).sum() / w.sum())


def test_nonlinear_step_is_nearer_the_exact_posterior_than_the_letkf(x64):
    """A Gaussian ensemble carried through a strongly nonlinear step and observed: the smoother's
    analysis mean is nearer the exact posterior mean of the state after the step than the LETKF's
    analysis of the propagated ensemble (which treats that skewed forecast as Gaussian)."""
    r = 0.5
    drift = lambda x: x + 0.3 * x**3                         # noqa: E731
    model = _scalar_model(drift, r)
    index, weight = local_obs(csf_jax.ring_localization(1, [0]), 2.0)
    rng = np.random.default_rng(0)
    ens = jnp.asarray(0.5 + 0.6 * rng.standard_normal((200, 200, 1)))
    y = drift(0.5 + 0.6 * rng.standard_normal(200)) + r * rng.standard_normal(200)
    exact = np.array([_exact_posterior_mean(drift, float(e.mean()), float(e.std(ddof=1)), v, r)
                      for e, v in zip(np.asarray(ens), y)])
    smooth = jax.jit(jax.vmap(lambda e, v: smoother_analysis(
        e, v[None], model, index, weight, [0], jnp.asarray(1.0))[0].mean()))(ens, jnp.asarray(y))
    filt = jax.jit(jax.vmap(lambda e, v: letkf_analysis(
        drift(e), v[None], model, jnp.asarray(index), weight).mean()))(ens, jnp.asarray(y))
    gaps = np.stack([np.abs(np.asarray(smooth) - exact), np.abs(np.asarray(filt) - exact)], 1)
    rms = np.sqrt((gaps**2).mean(0))
    assert rms[0] < 0.75 * rms[1]             # 0.069 against 0.110 (200 trials, seed 0)


def test_missing_step_carries_the_inflated_ensemble():
    model = csf_jax.problems.get("lorenz96_arctan", dim=20, num_steps=3, burn_in=0)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    obs = obs.at[1].set(jnp.nan)
    ens = model.initial_ensemble(jax.random.key(1), 10)
    loc = csf_jax.ring_localization(20, range(20))
    res = csf_jax.ienks(obs, ens, model=model, key=jax.random.key(2), localization=loc,
                        config=csf_jax.IEnKSConfig(4.0, 1.1), return_ensembles=True)
    before = res.ensembles[0]
    center = before.mean(0)
    expected = jax.vmap(model.drift)(center + 1.1 * (before - center))
    np.testing.assert_allclose(np.asarray(res.ensembles[1]), np.asarray(expected), atol=1e-5)
    its = np.asarray(res.info["iterations"])
    assert its[1] == 1 and its[0] > 1 and its[2] > 1        # arctan: Gauss-Newton iterates
    assert bool(res.finite.all())


def test_refuses_what_it_cannot_smooth():
    loc = csf_jax.ring_localization(8, range(8))
    noisy = csf_jax.problems.get("lorenz96", dim=8, num_steps=2, burn_in=0, process_std=0.1)
    _, obs = csf_jax.simulate(noisy, jax.random.key(0))
    ens = noisy.initial_ensemble(jax.random.key(1), 6)
    with pytest.raises(ValueError, match="perfect model"):
        csf_jax.ienks(obs, ens, model=noisy, key=jax.random.key(2), localization=loc)
    with pytest.raises(TypeError, match="localization"):
        csf_jax.ienks(obs, ens, model=noisy._replace(process_std=0.0), key=jax.random.key(2))
    with pytest.raises(TypeError, match="IEnKSConfig"):
        csf_jax.methods.ienks(loc, csf_jax.LETKFConfig())
    for bad in ({"iterations": 0}, {"tol": -1.0}, {"radius": 0.0}, {"adaptive": -1.0},
                {"iterations": 2.5}):
        with pytest.raises(ValueError, match="IEnKSConfig"):
            csf_jax.IEnKSConfig(**bad)
