"""The data's log-likelihood (``FilterResult.log_evidence``) against closed forms and large-N
estimates, and the observation laws' normalising constants against quadrature."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.special import logsumexp

import csf_jax
from csf_jax.problems.linear import linear_gaussian, to_model
from csf_jax.ssm import log_normalizer, normalized_log_likelihood


def stacked_log_likelihood(lg, obs) -> float:
    """``log N(y_1:K; mean, C)`` of the stacked linear-Gaussian model over the observed entries of
    ``obs (K, m)``: the record's exact log-likelihood, with no filter in between."""
    A, H, Q, R = (np.asarray(a, np.float64) for a in (lg.A, lg.H, lg.process_cov(), lg.obs_cov()))
    m, K = H.shape[0], obs.shape[0]
    powers = [np.linalg.matrix_power(A, k) for k in range(K + 1)]
    p0 = lg.p0_std ** 2 * np.eye(A.shape[0])
    mean = np.concatenate([H @ powers[k] @ lg.m0 for k in range(1, K + 1)])
    cov = np.zeros((K * m, K * m))
    for i in range(1, K + 1):
        for j in range(1, K + 1):
            c = powers[i] @ p0 @ powers[j].T
            for s in range(1, min(i, j) + 1):
                c = c + powers[i - s] @ Q @ powers[j - s].T
            cov[(i - 1) * m:i * m, (j - 1) * m:j * m] = H @ c @ H.T + (R if i == j else 0.0)
    y = np.asarray(obs, np.float64).reshape(-1)
    keep = ~np.isnan(y)
    r, S = y[keep] - mean[keep], cov[np.ix_(keep, keep)]
    return float(-0.5 * (r @ np.linalg.solve(S, r) + np.linalg.slogdet(2 * np.pi * S)[1]))


def _linear_case(dim=3, obs_dim=2, num_steps=15, seed=0, **kw):
    lg = linear_gaussian(dim, obs_dim, num_steps=num_steps, **kw)
    _, obs = csf_jax.simulate(to_model(lg), jax.random.key(seed))
    obs = np.array(obs, np.float64)
    obs[3, 0] = np.nan        # a partly missing observation
    obs[7, :] = np.nan        # a step without one
    return lg, jnp.asarray(obs)


def test_kalman_evidence_is_the_closed_form(x64):
    lg, obs = _linear_case()
    result = csf_jax.kalman_filter(obs, model=lg)
    assert result.log_evidence.shape == (obs.shape[0],)
    assert float(result.log_evidence[7]) == 0.0
    np.testing.assert_allclose(float(result.log_evidence.sum()), stacked_log_likelihood(lg, obs),
                               rtol=0, atol=1e-6)


def test_kalman_evidence_with_correlated_noises(x64):
    Q = [[0.2, 0.05, 0.0], [0.05, 0.1, 0.02], [0.0, 0.02, 0.3]]
    R = [[0.3, 0.1], [0.1, 0.2]]
    lg, obs = _linear_case(Q=Q, R=R, seed=1)
    result = csf_jax.kalman_filter(obs, model=lg)
    np.testing.assert_allclose(float(result.log_evidence.sum()), stacked_log_likelihood(lg, obs),
                               rtol=0, atol=1e-6)


def test_the_closed_form_can_fail(x64):
    """The check above sees a wrong noise: the Kalman filter of another model misses by far."""
    lg, obs = _linear_case()
    other = linear_gaussian(3, 2, num_steps=15, r_std=0.7)
    wrong = float(csf_jax.kalman_filter(obs, model=other).log_evidence.sum())
    assert abs(wrong - stacked_log_likelihood(lg, obs)) > 1.0


def test_enkf_evidence_approaches_kalman(x64):
    """d = 5: the EnKF's innovation density at N = 10,000 within 0.5% of the exact value."""
    lg, obs = _linear_case(dim=5, obs_dim=3, num_steps=20, seed=2)
    model = to_model(lg)
    exact = float(csf_jax.kalman_filter(obs, model=lg).log_evidence.sum())
    ensemble = model.initial_ensemble(jax.random.key(1), 10_000)
    enkf = csf_jax.ensemble_kalman_filter(obs, ensemble, model=model, key=jax.random.key(2))
    assert abs(float(enkf.log_evidence.sum()) - exact) < 0.005 * abs(exact)
    assert float(enkf.log_evidence[7]) == 0.0


def test_letkf_evidence_is_the_innovation_density(x64):
    """The LETKF's evidence (the innovation density of its forecast, unlocalised) near the exact
    one at N = 400 (its analysis is an N x N transform per site, so N stays moderate)."""
    lg, obs = _linear_case(dim=4, obs_dim=4, num_steps=10, seed=3)
    model = to_model(lg)
    exact = float(csf_jax.kalman_filter(obs, model=lg).log_evidence.sum())
    ensemble = model.initial_ensemble(jax.random.key(1), 400)
    loc = csf_jax.ring_localization(4, np.arange(4))
    letkf = csf_jax.letkf(obs, ensemble, model=model, key=jax.random.key(2), localization=loc,
                          config=csf_jax.LETKFConfig(radius=10.0))
    assert abs(float(letkf.log_evidence.sum()) - exact) < 0.03 * abs(exact)


@pytest.mark.slow
def test_particle_filter_evidence_on_the_pendulum():
    """Mean over 20 seeds at N = 1000 within 1 nat of a 10^6-particle estimate."""
    model = csf_jax.problems.get("pendulum")
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    big = csf_jax.particle_filter(obs, model.initial_ensemble(jax.random.key(1), 1_000_000),
                                  model=model, key=jax.random.key(2))
    reference = float(big.log_evidence.sum())

    def one(seed):
        ens = model.initial_ensemble(jax.random.fold_in(jax.random.key(3), seed), 1000)
        run = csf_jax.particle_filter(obs, ens, model=model, key=jax.random.key(seed))
        return run.log_evidence.sum()

    estimates = jax.vmap(one)(jnp.arange(20))
    assert abs(float(estimates.mean()) - reference) < 1.0
    assert float(estimates.std()) > 0.0       # the seeds differ: the mean is over 20 estimates


def test_no_observation_no_evidence():
    model = csf_jax.problems.get("pendulum", num_steps=6)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    obs = obs.at[2].set(jnp.nan)
    ens = model.initial_ensemble(jax.random.key(1), 200)
    for run in (csf_jax.particle_filter, csf_jax.ensemble_kalman_filter):
        ev = run(obs, ens, model=model, key=jax.random.key(2)).log_evidence
        assert float(ev[2]) == 0.0 and bool(jnp.all(ev[jnp.array([0, 1, 3])] != 0.0))


def test_a_noise_without_its_constant_gives_no_particle_evidence():
    model = csf_jax.problems.get("pendulum", num_steps=4)
    model = model._replace(obs_noise=model.obs_noise._replace(log_norm=None))
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 100)
    assert csf_jax.particle_filter(obs, ens, model=model, key=jax.random.key(2)).log_evidence \
        is None
    # the EnKF's innovation density needs only R
    assert csf_jax.ensemble_kalman_filter(obs, ens, model=model,
                                          key=jax.random.key(2)).log_evidence is not None


def _model_with(noise, obs_dim=1):
    return csf_jax.StateSpaceModel(
        name="probe", dim=1, obs_dim=obs_dim, num_steps=1, dt=1.0, drift=lambda x: x,
        observe=lambda x: jnp.repeat(x, obs_dim), process_std=0.1, obs_noise=noise,
        initial_truth=lambda k: jnp.zeros(1), initial_ensemble=lambda k, n: jnp.zeros((n, 1)))


@pytest.mark.parametrize("noise", [csf_jax.gaussian_noise(0.3), csf_jax.cauchy_noise(0.2),
                                   csf_jax.volatility_likelihood()],
                         ids=["gaussian", "cauchy", "volatility"])
def test_continuous_laws_are_normalised(noise, x64):
    """``exp(log p)`` integrates to 1 over y (quadrature; Cauchy through y = s tan(u))."""
    model = _model_with(noise)
    x = jnp.array([0.4])
    if noise.name == "cauchy":
        u = jnp.linspace(-math.pi / 2, math.pi / 2, 200_001)[1:-1]
        y, jac = 0.4 + 0.2 * jnp.tan(u), 0.2 / jnp.cos(u) ** 2
    else:
        y, jac = jnp.linspace(-12.0, 12.0, 200_001), jnp.ones(200_001)
    density = jnp.exp(jax.vmap(lambda v: normalized_log_likelihood(model, v[None], x))(y)) * jac
    du = (u[1] - u[0]) if noise.name == "cauchy" else (y[1] - y[0])
    np.testing.assert_allclose(float(jnp.sum(density) * du), 1.0, rtol=2e-4)


def test_poisson_is_normalised(x64):
    model = _model_with(csf_jax.poisson_likelihood())
    counts = jnp.arange(0.0, 200.0)
    p = jnp.exp(jax.vmap(lambda c: normalized_log_likelihood(model, c[None], jnp.array([1.3])))(
        counts))
    np.testing.assert_allclose(float(p.sum()), 1.0, rtol=1e-10)


def test_correlated_gaussian_is_normalised_on_observed_entries(x64):
    cov = np.array([[0.5, 0.2, 0.1], [0.2, 0.4, 0.0], [0.1, 0.0, 0.3]])
    model = _model_with(csf_jax.gaussian_noise_cov(cov), obs_dim=3)
    x = jnp.array([0.2])
    y = jnp.array([0.5, jnp.nan, -0.1])
    keep = np.array([0, 2])
    S = cov[np.ix_(keep, keep)]
    r = np.array([0.5, -0.1]) - 0.2
    exact = -0.5 * (r @ np.linalg.solve(S, r) + np.linalg.slogdet(2 * np.pi * S)[1])
    np.testing.assert_allclose(float(normalized_log_likelihood(model, y, x)), exact, rtol=1e-10)
    assert float(log_normalizer(model, jnp.full(3, jnp.nan))) == 0.0


def test_csf_evidence_near_the_exact_likelihood():
    """CSF's mixture evidence on a linear-Gaussian model within 2 nats of the exact record
    log-likelihood (the Kalman filter's), over 15 steps."""
    lg, obs = _linear_case(seed=4)
    obs = obs.astype(jnp.float32)
    model = to_model(lg)
    exact = float(csf_jax.kalman_filter(obs, model=lg).log_evidence.sum())
    ens = model.initial_ensemble(jax.random.key(1), 1000)
    csf = csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(2))
    assert abs(float(csf.log_evidence.sum()) - exact) < 2.0


@pytest.mark.slow
@pytest.mark.parametrize("name, settings", [("double_well", {"shock_count": 0}),
                                            ("pendulum", {})], ids=["double_well", "pendulum"])
def test_csf_evidence_near_a_large_particle_filter(name, settings):
    """Data drawn from the model itself (the double well without its truth's shock): CSF's
    summed log evidence at N = 1000 within 2 nats of a 10^6-particle filter's."""
    model = csf_jax.problems.get(name, **settings)
    _, obs = csf_jax.simulate(model, jax.random.key(1))
    big = csf_jax.particle_filter(obs, model.initial_ensemble(jax.random.key(11), 1_000_000),
                                  model=model, key=jax.random.key(3))
    ens = model.initial_ensemble(jax.random.key(21), 1000)
    csf = csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(5))
    assert abs(float(csf.log_evidence.sum()) - float(big.log_evidence.sum())) < 2.0


def test_paper_csf_gives_no_evidence():
    model = csf_jax.problems.get("double_well", num_steps=3)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 50)
    prior = csf_jax.load_pretrained("double_well")
    assert csf_jax.filter(prior, obs, ens, model=model, key=jax.random.key(2),
                          config=csf_jax.PAPER).log_evidence is None


def test_log_mean_weight_is_the_mean_in_log_space():
    from csf_jax.evidence import log_mean_weight
    w = jnp.array([-1.0, -2.0, -0.5, -3.0])
    np.testing.assert_allclose(float(log_mean_weight(w)), float(logsumexp(w) - jnp.log(4.0)),
                               rtol=1e-6)
