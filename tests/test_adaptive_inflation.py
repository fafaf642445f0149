"""The local filters' settings that adapt online: the EnKF-N's inflation (``adaptive``, on
``LETKFConfig`` and ``LocalTransformConfig``) and the LETKF's radius chosen by its evidence
(``LETKFConfig.radii``): what each estimates on draws whose law is known, and how the filters
take it."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax.filters.letkf import enkf_n_inflation, obs_tapers, radius_evidence
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


# --- the radius chosen online ------------------------------------------------------------------


def test_evidence_with_a_flat_taper_is_the_gaussian_log_density(x64):
    """With every taper entry 1 the evidence is ``log N(y; y_bar, Y'Y'^T / (N - 1) + R)`` up to
    ``-(m / 2) log 2 pi``; a missing entry drops out."""
    ens, y = _case(3, 1.0)
    ens, y = np.asarray(ens, np.float64)[:, :8] + 0.0, np.asarray(y, np.float64)[:8]
    model = to_model(linear_gaussian(8, 8, H=np.eye(8), r_std=0.5))
    got = radius_evidence(ens, y, model, np.ones((1, 8, 8)))[0]
    cov = np.cov(ens.T) + 0.25 * np.eye(8)
    r = y - ens.mean(0)
    want = -0.5 * r @ np.linalg.solve(cov, r) - 0.5 * np.linalg.slogdet(cov)[1]
    np.testing.assert_allclose(got, want, rtol=1e-10)
    y = y.copy()
    y[2] = np.nan
    keep = [i for i in range(8) if i != 2]
    sub = cov[np.ix_(keep, keep)]
    want = -0.5 * r[keep] @ np.linalg.solve(sub, r[keep]) - 0.5 * np.linalg.slogdet(sub)[1]
    np.testing.assert_allclose(radius_evidence(ens, y, model, np.ones((1, 8, 8)))[0], want,
                               rtol=1e-10)


@pytest.mark.parametrize("length, lo, hi", [(None, 0.0, 2.0),
                                            pytest.param(8.0, 4.0, 16.0, marks=pytest.mark.slow)])
def test_evidence_picks_a_radius_near_the_errors_correlation_length(length, lo, hi):
    """Forecast errors on a ring of 40 with Gaspari-Cohn correlations of half-width ``length``
    (None: uncorrelated), 20 members drawn from the same law: summed over 30 draws, the evidence
    is largest at a radius within ``[lo, hi]`` of the candidates 1 .. 16."""
    d, n = 40, 20
    radii = (1.0, 2.0, 4.0, 8.0, 16.0)
    loc = csf_jax.ring_localization(d, np.arange(d))
    corr = np.eye(d) if length is None else obs_tapers(loc, (length,))[0]
    chol = np.linalg.cholesky(corr + 1e-9 * np.eye(d))
    model = to_model(linear_gaussian(d, d, H=np.eye(d), r_std=0.3))
    tapers = obs_tapers(loc, radii)
    rng = np.random.default_rng(0)
    total = np.zeros(len(radii))
    for _ in range(30):
        ens = (chol @ rng.standard_normal((d, n))).T
        y = chol @ rng.standard_normal(d) + 0.3 * rng.standard_normal(d)
        total += np.asarray(radius_evidence(jnp.asarray(ens, jnp.float32),
                                            jnp.asarray(y, jnp.float32), model, tapers))
    assert lo <= radii[int(np.argmax(total))] <= hi, total


@pytest.mark.slow  # kept out of the default run's time budget: a limit case of the radius choice
def test_one_candidate_radius_is_the_fixed_radius():
    d = 20
    model = to_model(linear_gaussian(d, d, H=np.eye(d), r_std=0.5, q_std=0.3))
    loc = csf_jax.ring_localization(d, np.arange(d))
    truth, obs = csf_jax.simulate(model, jax.random.key(0), num_steps=6)
    ens = jax.random.normal(jax.random.key(1), (N, d))
    run = functools.partial(csf_jax.letkf, obs, ens, model=model, key=jax.random.key(2),
                            localization=loc)
    fixed = run(config=csf_jax.LETKFConfig(radius=3.0))
    one = run(config=csf_jax.LETKFConfig(radius=9.0, radii=(3.0,)))
    np.testing.assert_array_equal(one.mean, fixed.mean)
    several = csf_jax.LETKFConfig(radii=(1.0, 3.0, 8.0))
    a, b = run(config=several), run(config=several)
    np.testing.assert_array_equal(a.mean, b.mean)  # same key, same result
    assert set(np.unique(np.asarray(a.info["radius"]))) <= {1.0, 3.0, 8.0}


@pytest.mark.parametrize("bad", [(0.0,), (-1.0, 2.0), [2.0], (float("inf"),), (True,)])
def test_refuses_bad_radii(bad):
    with pytest.raises(ValueError, match="radii must be a tuple"):
        csf_jax.LETKFConfig(radii=bad)
