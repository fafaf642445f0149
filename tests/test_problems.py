"""The paper's problems: registry, simulation, noise models, shocks, and a user-defined problem."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax import problems
from csf_jax.ssm import StateSpaceModel, cauchy_matched_std, cauchy_noise, gaussian_noise

SIZES = {"double_well": 1, "triple_well": 1, "cauchy": 5, "cubic10_indep": 10,
         "cubic10_corr": 10, "cubic20_indep": 20, "cubic20_corr": 20}
STEPS = {"double_well": 100, "triple_well": 100}


@pytest.mark.parametrize("name", problems.NAMES)
def test_simulate_shapes_and_shocks(name):
    model = problems.get(name)
    d = SIZES[name]
    K = STEPS.get(name, 200)
    assert (model.dim, model.obs_dim, model.num_steps) == (d, d, K)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    assert truth.shape == (K + 1, d) and obs.shape == (K, d)
    assert bool(jnp.isfinite(truth).all()) and bool(jnp.isfinite(obs).all())
    times = model.shock_times(jax.random.key(1), K)
    cfg = problems.config(name)
    assert int(times.sum()) == cfg.shock_count
    assert not bool(times[: int(0.2 * K)].any()) and not bool(times[int(0.8 * K):].any())
    again = csf_jax.simulate(model, jax.random.key(0))
    np.testing.assert_array_equal(truth, again[0])


def test_registry_and_overrides():
    assert set(problems.NAMES) == set(SIZES)
    short = problems.get("cubic10_corr", num_steps=7)
    assert short.num_steps == 7 and short.name == "cubic10_corr"
    assert problems.get("double_well") is problems.get("double_well")  # cached: jit reuse
    with pytest.raises(KeyError, match="unknown problem"):
        problems.get("quadruple_well")
    with pytest.raises(ValueError, match="wells"):
        problems.config("double_well", wells="quad")


def test_double_well_drift_keeps_state_and_has_wells():
    model = problems.get("double_well")
    for x in (-1.0, 1.0):  # fixed points of the Euler map
        assert float(model.drift(jnp.array([x]))[0]) == pytest.approx(x, abs=1e-6)
    # C = 1.5, dt = 0.1: x - 0.6 x (x^2 - 1)
    assert float(model.drift(jnp.array([0.5]))[0]) == pytest.approx(0.5 + 0.6 * 0.5 * 0.75)
    literal = problems.get("double_well", include_state=False)
    assert float(literal.drift(jnp.array([1.0]))[0]) == pytest.approx(0.0, abs=1e-6)
    assert model.process_std == pytest.approx(math.sqrt(0.1) * 0.2)


def test_triple_well_minima():
    model = problems.get("triple_well")
    for x in (-1.0, 0.5, 1.0):
        assert float(model.drift(jnp.array([x]))[0]) == pytest.approx(x, abs=1e-6)


def test_correlated_drift():
    model = problems.get("cubic10_corr")
    x = jnp.linspace(-1.0, 1.0, 10)
    A = -0.5 * np.eye(10) + 0.1 * np.eye(10, k=1)
    np.testing.assert_allclose(model.drift(x), x + 0.01 * (A @ x + np.cos(x)), rtol=1e-5)


def test_cauchy_likelihood_and_gaussian_stand_in():
    noise = cauchy_noise(0.0544)
    r = jnp.array([0.0, 0.0544, -1.0])
    expected = -np.sum(np.log1p((np.asarray(r) / 0.0544) ** 2))
    assert float(noise.log_prob(r)) == pytest.approx(expected, rel=1e-6)
    # Same central 68% interval as N(0, 0.1^2): the stand-in std 0.1.
    assert noise.gaussian_std == pytest.approx(0.1, abs=1e-3)
    assert cauchy_matched_std(1.0) == pytest.approx(1.0 / 0.544, rel=2e-3)
    draws = noise.sample(jax.random.key(0), (200000,))
    frac = float(jnp.mean(jnp.abs(draws) < noise.gaussian_std))
    assert frac == pytest.approx(math.erf(1 / math.sqrt(2)), abs=0.005)
    assert problems.get("cauchy").obs_noise.name == "cauchy"


def test_gaussian_noise():
    noise = gaussian_noise(0.1)
    assert float(noise.log_prob(jnp.array([0.1, 0.2]))) == pytest.approx(-0.5 * 5.0, rel=1e-6)
    assert noise.gaussian_std == 0.1


def test_pf_loses_track_after_shocks():
    """The shocks are strong enough that a 1000-particle SIR filter loses track in a sizable
    fraction of double-well runs (paper: PF RMSE 1.1 against CSF 0.04)."""
    model = problems.get("double_well")
    keys = jax.random.split(jax.random.key(0), 10)
    truth, obs = jax.vmap(lambda k: csf_jax.simulate(model, k))(keys)
    ens = jax.vmap(lambda k: model.initial_ensemble(k, 1000))(keys)
    pf = jax.vmap(lambda o, e, k: csf_jax.particle_filter(o, e, model=model, key=k))(
        obs, ens, keys)
    # Lost: the last 10 steps' mean error exceeds 1 (the wells are 2 apart).
    final_err = jnp.abs(pf.mean[:, -10:, 0] - truth[:, -10:, 0]).mean(axis=1)
    lost = int((final_err > 1.0).sum())
    assert lost >= 3, f"PF lost track in only {lost}/10 runs"


def _my_problem():
    """The README's user-defined problem: a pendulum whose angle is observed."""

    def drift(x):
        return jnp.array([x[0] + 0.1 * x[1], x[1] - 0.1 * jnp.sin(x[0])])

    return StateSpaceModel(
        name="pendulum", dim=2, obs_dim=1, num_steps=50, dt=0.1, drift=drift,
        observe=lambda x: x[:1], process_std=0.1, obs_noise=gaussian_noise(0.1),
        initial_truth=lambda key: jnp.array([1.0, 0.0]) + 0.1 * jax.random.normal(key, (2,)),
        initial_ensemble=lambda key, n: jnp.array([1.0, 0.0]) + 0.1 * jax.random.normal(key, (n, 2)),
    )


def test_user_defined_problem_runs_everywhere():
    model = _my_problem()
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    assert truth.shape == (51, 2) and obs.shape == (50, 1)
    ens = model.initial_ensemble(jax.random.key(1), 64)
    for run in (lambda: csf_jax.particle_filter(obs, ens, model=model, key=jax.random.key(2)),
                lambda: csf_jax.ensemble_kalman_filter(obs, ens, model=model,
                                                       key=jax.random.key(2)),
                lambda: csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(2),
                                       config=csf_jax.CSFConfig(sampler=csf_jax.SamplerConfig(reverse_steps=100)))):
        r = run()
        assert r.mean.shape == (50, 2)
        assert float(csf_jax.rmse(r.mean, truth[1:])) < 1.0


def test_moderate_zoo_models_are_sign_blind_and_stable():
    """The zoo's models of moderate dimension: the well chain's split step stays finite from any
    state an update reaches and keeps both wells; the Lorenz-96 sensors cannot tell x from -x."""
    from csf_jax.problems import zoo

    chain = problems.get("well_chain")
    far = jnp.linspace(-1e3, 1e3, chain.dim)
    assert bool(jnp.isfinite(chain.drift(far)).all())
    assert float(jnp.max(jnp.abs(chain.drift(far)))) < 10.0
    assert bool(jnp.all(chain.drift(jnp.ones(chain.dim)) > 0.5))
    assert bool(jnp.all(chain.drift(-jnp.ones(chain.dim)) < -0.5))
    for name in ("lorenz96_abs", "lorenz96_square"):
        model = problems.get(name)
        x = model.initial_truth(jax.random.key(0))
        np.testing.assert_allclose(model.observe(x), model.observe(-x))
        assert model.obs_dim == model.dim // 2
    assert set(zoo.MODERATE) <= set(problems.ZOO)


@pytest.mark.parametrize("name", [*problems.NAMES, *problems.ZOO])
def test_a_model_first_built_inside_jit_works_outside_it(name):
    # the builders are cached: what one keeps from a trace must not be a tracer
    built = {}

    @jax.jit
    def trace(x):
        built["model"] = problems.get(name, num_steps=3)
        return x

    trace(0.0)
    model = problems.get(name, num_steps=3)
    assert model is built["model"]
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    assert truth.shape == (4, model.dim) and bool(jnp.isfinite(truth).all())
