"""CSF's mixture prior: component evidences against their closed form, the selection's limits,
the Bayes-factor memory, and CSF with it against the Kalman filter."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import make_linear_case

import csf_jax
from csf_jax import CSFConfig, MixtureConfig, mixture
from csf_jax.problems.linear import linear_gaussian, to_model


def _gaussian_log_evidence(y, H, mean, cov, R):
    """``log N(y; H mean, H cov H^T + R)`` plus ``1/2 log det(2 pi R)``: the evidence with the
    likelihood's normalising constant left out, as ``log_likelihood`` leaves it out."""
    S = H @ cov @ H.T + R
    r = y - H @ mean
    _, logdet_s = np.linalg.slogdet(2 * np.pi * S)
    _, logdet_r = np.linalg.slogdet(2 * np.pi * R)
    return -0.5 * r @ np.linalg.solve(S, r) - 0.5 * logdet_s + 0.5 * logdet_r


def test_component_evidence_matches_the_gaussian_closed_form(x64):
    """Linear sensor, Gaussian noise: the Laplace proposal is the exact posterior, so every
    importance weight equals the evidence; the estimate matches ``N(y; H mu, H B H^T + R)`` to
    1e-9 for components of different means and covariances (what the selection compares)."""
    lg = linear_gaussian(3, 2, r_std=0.4)
    model = to_model(lg)
    y = jnp.array([0.7, -1.2])
    rng = np.random.default_rng(0)
    means = rng.standard_normal((4, 3))
    for scale in (0.1, 1.0, 5.0):
        cov = scale * np.diag([1.0, 2.0, 0.5])
        prec = jnp.asarray(np.linalg.inv(cov))
        log_z, draws, _, _ = mixture._component_evidence(model, y, jax.random.key(0), jnp.asarray(means),
                                                   prec, 2, 16, 1.0)
        exact = [_gaussian_log_evidence(np.asarray(y), lg.H, mu, cov, lg.obs_cov()) for mu in means]
        np.testing.assert_allclose(np.asarray(log_z), exact, atol=1e-9)
        assert draws.shape == (4, 3)


@pytest.mark.slow
def test_component_evidence_is_consistent_for_a_nonlinear_sensor(x64):
    """Cubic sensor: the importance estimate converges to the quadrature value of
    ``int N(x; mu, b) exp(-(y - x^3)^2 / (2 r^2)) dx`` (1-D), within 0.05 in log at 4096
    proposals; the Laplace value alone is off by more."""
    model = csf_jax.problems.get("double_well")
    mu, b, y = 0.6, 0.2 ** 2, jnp.array([0.5])
    grid = np.linspace(mu - 10 * np.sqrt(b), mu + 10 * np.sqrt(b), 200001)
    dens = (np.exp(-0.5 * (grid - mu) ** 2 / b) / np.sqrt(2 * np.pi * b)
            * np.exp(-0.5 * (0.5 - grid ** 3) ** 2 / 0.1 ** 2))
    exact = np.log(np.sum(dens) * (grid[1] - grid[0]))
    log_z, _, _, _ = mixture._component_evidence(model, y, jax.random.key(1), jnp.array([[mu]]),
                                           jnp.array([[1 / b]]), 10, 4096, 1.0)
    assert abs(float(log_z[0]) - exact) < 0.05, (float(log_z[0]), exact)


@pytest.mark.slow
def test_selection_limits():
    """Without particle and shock components every member samples the ensemble component. A
    bimodal ensemble observed in one well: the particles explain y better than the ensemble's
    Gaussian (measured log Bayes factor 2.4, particle weight 0.92 at even prior odds), and the
    members drawn from particle components sit in the observed well."""
    model = csf_jax.problems.get("double_well")
    key = jax.random.key(0)
    centers = jnp.concatenate([jnp.full((50, 1), -1.0), jnp.full((50, 1), 1.0)])
    prior_ens = centers + 0.05 * jax.random.normal(key, centers.shape)
    cov = jnp.cov(prior_ens.T).reshape(1, 1)
    off = MixtureConfig(particles=False, shock_hazard=0.0)
    sel = mixture.select(model, off, key, jnp.array([1.0]), centers, prior_ens, cov, 0.0, 0.0, 1.0)
    assert bool(jnp.all(sel.kind == 1)) and float(sel.particle_weight) == 0.0
    on = MixtureConfig(shock_hazard=0.0)
    sel = mixture.select(model, on, key, jnp.array([1.0]), centers, prior_ens, cov, 0.0, 0.0, 1.0)
    assert float(sel.particle_weight) > 0.85 and float(sel.log_bf) > 1.5
    # the particle members sit in the observed well: y = x^3 = 1
    chosen = sel.draws[sel.kind == 0]
    assert float(jnp.min(chosen)) > 0.5


@pytest.mark.slow
def test_shock_component_takes_over_after_a_jump():
    """An observation far outside the ensemble's reach: the shock components win the evidence."""
    model = csf_jax.problems.get("cubic10_indep", dim=3)
    key = jax.random.key(0)
    centers = 0.1 * jax.random.normal(key, (200, 3))
    prior_ens = centers + 0.1 * jax.random.normal(jax.random.key(1), (200, 3))
    cov = jnp.cov(prior_ens.T)
    y = jnp.full((3,), 8.0)  # x = 2 in every coordinate
    sel = mixture.select(model, MixtureConfig(), key, y, centers, prior_ens, cov, 0.0, 2.0, 1.0)
    assert float(sel.shock_weight) > 0.9
    quiet = mixture.select(model, MixtureConfig(), key, jnp.zeros(3) + 1e-3, centers, prior_ens,
                           cov, 0.0, 2.0, 1.0)
    assert float(quiet.shock_weight) < 0.01


def test_memory_accumulates_with_forgetting():
    cfg = MixtureConfig(memory=0.5, particle_logodds=1.0)
    acc, odds = mixture.next_odds(cfg, 2.0, 3.0)
    assert float(acc) == 4.0 and float(odds) == 5.0


@pytest.mark.slow
def test_mixture_csf_tracks_kalman(x64):
    """``csf_jax.ROBUST`` (the mixture prior) on a linear-Gaussian model, N = 300: within a
    fraction of the Kalman std of the Kalman mean."""
    case = make_linear_case(2, 300, with_prior=True)
    r = csf_jax.filter(None, case.obs, case.ensemble, problem=case.model, key=jax.random.key(5),
                       config=csf_jax.ROBUST)
    print(case.errors(r.mean, r.std))
    err = case.errors(r.mean, r.std)
    assert err.mean_rms < 0.25 and err.mean_max < 0.7, err
    assert err.std_rms < 0.25, err
    assert set(r.info) == {"particle_weight", "shock_weight"}
    assert r.info["particle_weight"].shape == (case.obs.shape[0],)


def test_bad_mixture_config_is_refused():
    for bad in (dict(memory=1.0), dict(shock_hazard=-0.1), dict(iterations=0),
                dict(shock_scales=()), dict(shock_scales=(1.0, -2.0)),
                dict(particle_logodds=float("nan"))):
        with pytest.raises(ValueError, match="MixtureConfig"):
            MixtureConfig(**bad)
    with pytest.raises(TypeError, match="mixture"):
        CSFConfig(mixture={"memory": 0.5})
    assert CSFConfig().mixture is None and csf_jax.ROBUST.mixture == MixtureConfig()
    assert not csf_jax.ROBUST.adaptive_inflation
