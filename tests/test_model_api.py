"""The model API beyond ``y = h(x) + w``: time-varying models with inputs (``Step``), non-additive
likelihoods (``Likelihood``), and the one driver every filter runs on; checked against closed
forms (a Kalman filter with inputs, a 1-D grid filter) and for clear errors at the boundary."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax import problems
from csf_jax.problems.linear import linear_gaussian
from csf_jax.ssm import StateSpaceModel, gaussian_noise

A, Q_STD, R_STD, K = 0.9, 0.5, 0.5, 25


def _start(mean, std):
    def truth(key):
        return mean + std * jax.random.normal(key, (1,))

    def ensemble(key, n):
        return mean + std * jax.random.normal(key, (n, 1))

    return truth, ensemble


def controlled(process_std=Q_STD, obs_noise=None, observe=None):
    """``x_k = A x_{k-1} + u_k + v_k``, ``y_k = x_k + w_k`` (1-D), the input ``u_k`` a per-step
    array; ``observe`` optional ``(x, step) -> eta``."""
    truth, ensemble = _start(0.0, 1.0)
    return StateSpaceModel(
        "controlled", 1, 1, K, 1.0, lambda x, step: A * x + step.u,
        observe if observe is not None else (lambda x, step: x), process_std,
        obs_noise if obs_noise is not None else gaussian_noise(R_STD), truth, ensemble,
        time_varying=True)


def kalman_with_inputs(obs, u):
    """The exact filter of ``controlled()``: means and variances ``(K,)``."""
    m, p = 0.0, 1.0
    means, variances = [], []
    for y, u_k in zip(np.asarray(obs)[:, 0], np.asarray(u)[:, 0]):
        m, p = A * m + u_k, A * A * p + Q_STD ** 2
        gain = p / (p + R_STD ** 2)
        m, p = m + gain * (y - m), (1.0 - gain) * p
        means.append(m)
        variances.append(p)
    return np.array(means), np.array(variances)


def _inputs():
    return 2.0 * jnp.sin(0.5 * jnp.arange(K, dtype=jnp.float32))[:, None]


def test_simulate_threads_inputs_and_the_time_index():
    model = controlled(process_std=0.0)
    u = _inputs()
    truth, obs = csf_jax.simulate(model, jax.random.key(0), inputs=u)
    assert truth.shape == (K + 1, 1) and obs.shape == (K, 1)
    x = float(truth[0, 0])
    for k in range(K):
        x = A * x + float(u[k, 0])
        assert float(truth[k + 1, 0]) == pytest.approx(x, rel=1e-5, abs=1e-5)
    ungm = problems.get("ungm", process_var=0.0, num_steps=6)
    truth, _ = csf_jax.simulate(ungm, jax.random.key(1))
    x = float(truth[0, 0])
    for k in range(1, 7):  # k = 1 .. K: x_k = f(x_{k-1}, k)
        x = 0.5 * x + 25 * x / (1 + x * x) + 8 * np.cos(1.2 * k)
        assert float(truth[k, 0]) == pytest.approx(x, rel=1e-4, abs=1e-4)


@pytest.mark.parametrize("method", ["csf", pytest.param("csf_paper", marks=pytest.mark.slow),
                                    "pf", "enkf"])
def test_filters_with_inputs_match_the_kalman_filter(method):
    """On a linear-Gaussian model driven by inputs, every ensemble filter's mean is within a few
    posterior stds' Monte Carlo error of the exact (Kalman) mean, with the inputs applied at the
    right steps: dropping them would move the mean by several posterior stds."""
    model = controlled()
    u = _inputs()
    _, obs = csf_jax.simulate(model, jax.random.key(3), inputs=u)
    ens = model.initial_ensemble(jax.random.key(4), 400)
    kw = dict(model=model, key=jax.random.key(5), inputs=u)
    run = {"csf": lambda: csf_jax.filter(None, obs, ens, **kw),
           "csf_paper": lambda: csf_jax.filter(None, obs, ens, config=csf_jax.PAPER, **kw),
           "pf": lambda: csf_jax.particle_filter(obs, ens, **kw),
           "enkf": lambda: csf_jax.ensemble_kalman_filter(obs, ens, **kw)}[method]
    mean = np.asarray(run().mean[:, 0])
    exact, var = kalman_with_inputs(obs, u)
    z = (mean - exact) / np.sqrt(var)
    print(method, np.sqrt(np.mean(z ** 2)))
    assert np.sqrt(np.mean(z ** 2)) < 0.15, z
    shifted, _ = kalman_with_inputs(obs, np.zeros_like(u))
    assert np.sqrt(np.mean(((shifted - exact) / np.sqrt(var)) ** 2)) > 1.0


def test_inputs_are_checked_at_the_boundary():
    model = controlled()
    u = _inputs()
    _, obs = csf_jax.simulate(model, jax.random.key(0), inputs=u)
    ens = model.initial_ensemble(jax.random.key(1), 20)
    with pytest.raises(ValueError, match="leading axis"):
        csf_jax.particle_filter(obs, ens, model=model, key=jax.random.key(0), inputs=u[:-1])
    fixed = problems.get("pendulum")
    _, obs_f = csf_jax.simulate(fixed, jax.random.key(0))
    ens_f = fixed.initial_ensemble(jax.random.key(1), 20)
    with pytest.raises(ValueError, match="not time-varying"):
        csf_jax.filter(None, obs_f, ens_f, model=fixed, key=jax.random.key(0),
                       inputs=jnp.zeros((obs_f.shape[0], 1)))
    with pytest.raises(ValueError, match="not time-varying"):
        csf_jax.simulate(fixed, jax.random.key(0), inputs=jnp.zeros((5, 1)))
    with pytest.raises(ValueError, match="steps but num_steps"):
        csf_jax.simulate(model, jax.random.key(0), num_steps=K + 1, inputs=u)


def grid_filter(model, obs, grid, prior_std):
    """Near-exact filtering means ``(K,)`` of a 1-D additive-Gaussian-dynamics model on ``grid``:
    ``p(x_k | y_1..k)`` by quadrature (``prior_std``: the initial state's std about 0)."""
    grid = np.asarray(grid, np.float64)
    dx = grid[1] - grid[0]
    p = np.exp(-0.5 * (grid / prior_std) ** 2)
    f = np.asarray(jax.vmap(model.drift)(jnp.asarray(grid[:, None], jnp.float32)))[:, 0]
    kernel = np.exp(-0.5 * ((grid[:, None] - f[None, :]) / model.process_std) ** 2)
    means = []
    for y in np.asarray(obs):
        p = kernel @ p
        if np.isfinite(y).all():
            loglik = np.asarray(jax.vmap(lambda x: csf_jax.log_likelihood(model, jnp.asarray(y),
                                                                           x))(
                jnp.asarray(grid[:, None], jnp.float32)), np.float64)
            p = p * np.exp(loglik - loglik.max())
        p = p / (p.sum() * dx)
        means.append(float(np.sum(grid * p) * dx))
    return np.array(means)


def _poisson_1d():
    truth, ensemble = _start(0.0, 0.8)
    return StateSpaceModel("poisson_1d", 1, 1, 30, 1.0, lambda x: 0.9 * x, lambda x: 1.0 + x,
                           0.35, csf_jax.poisson_likelihood(), truth, ensemble)


@pytest.mark.slow
def test_poisson_likelihood_filters_match_a_grid_filter():
    """Counts ``y ~ Poisson(exp(1 + x))``: CSF (defaults and ``PAPER``, no network) and the PF
    against a quadrature filter, including steps with a missing count; the EnKF, on its Gaussian
    stand-in, is further off."""
    model = _poisson_1d()
    _, obs = csf_jax.simulate(model, jax.random.key(2))
    assert bool(jnp.all(obs == jnp.round(obs))) and bool(jnp.all(obs >= 0))
    obs = obs.at[jnp.array([4, 11])].set(jnp.nan)
    exact = grid_filter(model, obs, np.linspace(-6, 6, 2401), 0.8)
    ens = model.initial_ensemble(jax.random.key(3), 500)
    kw = dict(model=model, key=jax.random.key(4))
    err = {}
    for name, fn in (("csf", lambda: csf_jax.filter(None, obs, ens, **kw)),
                     ("csf_paper", lambda: csf_jax.filter(None, obs, ens, config=csf_jax.PAPER,
                                                          **kw)),
                     ("pf", lambda: csf_jax.particle_filter(obs, ens, **kw)),
                     ("enkf", lambda: csf_jax.ensemble_kalman_filter(obs, ens, **kw))):
        err[name] = float(np.sqrt(np.mean((np.asarray(fn().mean[:, 0]) - exact) ** 2)))
    print(err)
    assert err["csf"] < 0.05 and err["csf_paper"] < 0.05 and err["pf"] < 0.05, err
    assert err["enkf"] > max(err["csf"], err["csf_paper"]), err


def test_a_likelihood_without_a_gaussian_standin_is_refused_by_kalman_type_filters():
    lik = csf_jax.poisson_likelihood()._replace(mean=None, variance=None)
    model = _poisson_1d()._replace(obs_noise=lik)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 50)
    with pytest.raises(ValueError, match="Gaussian stand-in"):
        csf_jax.ensemble_kalman_filter(obs, ens, model=model, key=jax.random.key(0))
    with pytest.raises(ValueError, match="Gaussian stand-in"):
        csf_jax.letkf(obs, ens, model=model, key=jax.random.key(0),
                      localization=csf_jax.ring_localization(1, [0]))
    with pytest.raises(ValueError, match="Gaussian stand-in"):  # the adaptive inflation's
        csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(0), config=csf_jax.PAPER)
    result = csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(0))
    assert bool(jnp.isfinite(result.mean).all())


def test_kalman_filter_takes_only_a_linear_state_space_model():
    lg = linear_gaussian(2, 2)
    from csf_jax.problems.linear import to_model
    np.testing.assert_array_equal(csf_jax.kalman_filter(jnp.zeros((3, 2)), model=to_model(lg)).mean,
                                  csf_jax.kalman_filter(jnp.zeros((3, 2)), model=lg).mean)
    with pytest.raises(TypeError, match="LinearGaussian"):
        csf_jax.kalman_filter(jnp.zeros((3, 1)), model=problems.get("pendulum"))


def test_driver_reports_progress_once_per_step():
    model = problems.get("pendulum", num_steps=8)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 64)
    seen = []
    csf_jax.particle_filter(obs, ens, model=model, key=jax.random.key(2),
                            progress=lambda k: seen.append(int(k)))
    jax.effects_barrier()
    assert sorted(seen) == list(range(8))


def test_info_holds_what_the_result_docstring_lists():
    """``FilterResult.info`` per filter, as its docstring lists it: the particle filter's ESS in
    ``ess`` (info None); the Kalman filter's covariances only from ``kalman_filter_cov``; the EnKF
    and CSF without the mixture (``csf_jax.PAPER``) report none. (The default CSF's mixture
    weights: the slow test below.)"""
    from csf_jax.filters.kalman import kalman_filter_cov
    from csf_jax.problems.linear import to_model
    lg = linear_gaussian(2, 1, num_steps=3)
    model = to_model(lg)
    obs = jnp.zeros((3, 1))
    ens = model.initial_ensemble(jax.random.key(1), 16)
    key = jax.random.key(2)
    pf = csf_jax.particle_filter(obs, ens, model=model, key=key)
    assert pf.info is None and pf.ess.shape == (3,)
    for result in (csf_jax.kalman_filter(obs, model=lg),
                   csf_jax.run(csf_jax.methods.kalman(), obs, None, model=lg, key=key),
                   csf_jax.ensemble_kalman_filter(obs, ens, model=model, key=key),
                   csf_jax.filter(None, obs, ens, model=model, key=key, config=csf_jax.CSFConfig(
                       sampler=csf_jax.SamplerConfig(reverse_steps=2),
                       inflation=csf_jax.PAPER.inflation, prior=csf_jax.PAPER.prior))):
        assert result.info is None and result.ess is None
    assert kalman_filter_cov(obs, lg)[1].shape == (3, 2, 2)


@pytest.mark.slow
def test_csf_reports_its_mixture_weights_and_is_reproducible():
    model = problems.get("pendulum", num_steps=8)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 64)
    run = lambda: csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(2))
    result = run()
    assert set(result.info) == {"particle_weight", "shock_weight", "dropped"}
    for v in result.info.values():
        assert v.shape == (8,) and bool(((v >= 0) & (v <= 1)).all())
    np.testing.assert_array_equal(result.mean, run().mean)


def _zoo_case(name):
    model = problems.get(name, num_steps=5)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    assert truth.shape == (6, model.dim) and obs.shape == (5, model.obs_dim)
    assert bool(jnp.isfinite(truth).all()) and bool(jnp.isfinite(obs).all())
    return model, obs


@pytest.mark.parametrize("name", sorted(problems.ZOO))
def test_zoo_models_simulate(name):
    _zoo_case(name)
    with pytest.raises(TypeError, match="no field"):
        problems.get(name, no_such_field=1)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(problems.ZOO))
def test_zoo_models_filter(name):
    model, obs = _zoo_case(name)
    ens = model.initial_ensemble(jax.random.key(1), 32)
    prior = None if model.process_noise is None else csf_jax.gaussian_prior()
    for config in (csf_jax.CSFConfig(), csf_jax.PAPER):
        result = csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(2),
                                config=config, prior=prior)
        assert result.mean.shape == (5, model.dim) and bool(jnp.isfinite(result.mean).all())
