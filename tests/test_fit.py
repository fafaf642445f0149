"""Parameter learning: ``ParametricModel`` (a model's numbers traced through the filters' scan)
and ``csf_jax.fit`` (maximum likelihood through the filters' log evidence)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax.filters import driver
from csf_jax.problems.linear import LinearGaussian, linear_gaussian, to_model

LG = linear_gaussian(1, q_std=0.3, r_std=0.5, num_steps=100)
THETA = {"q": 0.3, "r": 0.5}


def build_lg(theta):
    """The linear model at ``theta`` as a ``LinearGaussian`` (the Kalman filter's)."""
    return LinearGaussian(LG.A, LG.H, theta["q"], theta["r"], LG.m0, LG.p0_std, LG.num_steps,
                          LG.name)


def build(theta):
    """The same model as a ``StateSpaceModel`` (the ensemble filters')."""
    return to_model(LG)._replace(process_std=theta["q"],
                                 obs_noise=csf_jax.gaussian_noise(theta["r"]))


def _evidence(method, obs, ensemble, theta, key=0):
    model = csf_jax.ParametricModel(build, theta)
    return csf_jax.run(method, obs, ensemble, model=model, key=jax.random.key(key),
                       check_finite=False).log_evidence.sum()


def _kalman_evidence(obs, theta):
    return csf_jax.kalman_filter(obs, model=csf_jax.ParametricModel(build_lg, theta)
                                 ).log_evidence.sum()


def _central_differences(f, theta, eps=1e-5):
    out = {}
    for name in theta:
        up, down = dict(theta), dict(theta)
        up[name], down[name] = theta[name] + eps, theta[name] - eps
        out[name] = float((f(up) - f(down)) / (2 * eps))
    return out


def _theta(dtype):
    return {k: jnp.asarray(v, dtype) for k, v in THETA.items()}


def test_concrete_theta_filters_as_the_model_it_builds(linear_obs):
    """A concrete ParametricModel gives the very numbers of the ordinary model it builds (the
    EnKF, the particle filter, the LETKF, the Kalman filter); with progress, the compilation is
    announced on stderr."""
    obs = jnp.asarray(linear_obs(LG, 0), jnp.float32)
    ensemble = to_model(LG).initial_ensemble(jax.random.key(1), 64)
    for method in (csf_jax.methods.enkf(), csf_jax.methods.pf()):
        plain = csf_jax.run(method, obs, ensemble, model=to_model(LG), key=jax.random.key(2))
        traced = csf_jax.run(method, obs, ensemble, model=csf_jax.ParametricModel(build, THETA),
                             key=jax.random.key(2))
        np.testing.assert_allclose(traced.mean, plain.mean, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(traced.log_evidence, plain.log_evidence, rtol=1e-6, atol=1e-5)
    letkf = csf_jax.methods.letkf(localization=csf_jax.ring_localization(1, [0]))
    plain = csf_jax.run(letkf, obs, ensemble, model=to_model(LG), key=jax.random.key(2))
    traced = csf_jax.run(letkf, obs, ensemble, model=csf_jax.ParametricModel(build, THETA),
                         key=jax.random.key(2), progress=lambda k: None)
    np.testing.assert_allclose(traced.mean, plain.mean, rtol=1e-6, atol=1e-6)
    plain = csf_jax.kalman_filter(obs, model=LG)
    traced = csf_jax.kalman_filter(obs, model=csf_jax.ParametricModel(build_lg, THETA))
    np.testing.assert_allclose(traced.log_evidence, plain.log_evidence, rtol=1e-6, atol=1e-5)


def test_new_values_reuse_one_compilation(linear_obs):
    """Concrete calls at three values of theta compile the filter's scan once."""
    obs = jnp.asarray(linear_obs(LG, 0), jnp.float32)
    ensemble = to_model(LG).initial_ensemble(jax.random.key(1), 32)
    method = csf_jax.methods.enkf(1.01)   # a config no other test compiles
    before = driver._scan_parametric._cache_size()
    values = [float(_evidence(method, obs, ensemble, {"q": q, "r": 0.5}))
              for q in (0.2, 0.3, 0.4)]
    assert driver._scan_parametric._cache_size() - before == 1
    assert len(set(values)) == 3


def test_vmap_over_a_grid_of_50_values_traces_once(linear_obs):
    """``jax.jit(jax.vmap(...))`` over 50 noise levels: one trace (so one compilation) serves a
    second grid too, and every value is the concrete run's."""
    obs = jnp.asarray(linear_obs(LG, 0), jnp.float32)
    ensemble = to_model(LG).initial_ensemble(jax.random.key(1), 32)
    method = csf_jax.methods.enkf()
    traces = []

    def evidence(r):
        traces.append(1)
        return _evidence(method, obs, ensemble, {"q": 0.3, "r": r})

    sweep = jax.jit(jax.vmap(evidence))
    grid = jnp.linspace(0.2, 1.0, 50)
    first = sweep(grid)
    sweep(grid + 0.01)
    assert len(traces) == 1 and first.shape == (50,)
    for i in (0, 31):
        np.testing.assert_allclose(first[i], _evidence(method, obs, ensemble,
                                                       {"q": 0.3, "r": float(grid[i])}),
                                   rtol=1e-5)
    # the likelihood peaks near the truth (r = 0.5)
    assert 0.3 < float(grid[jnp.argmax(first)]) < 0.7


def test_kalman_gradient_matches_finite_differences(x64, linear_obs):
    obs = jnp.asarray(linear_obs(LG, 0))
    theta = _theta(jnp.float64)
    grad = jax.grad(lambda t: _kalman_evidence(obs, t))(theta)
    fd = _central_differences(lambda t: _kalman_evidence(obs, t), theta)
    for name in theta:
        assert float(grad[name]) == pytest.approx(fd[name], rel=0.01)


def test_kalman_takes_a_traced_full_covariance(x64, linear_obs):
    """A ``LinearGaussian`` with a traced ``Q`` (d = 2): the gradient in its entries matches
    finite differences."""
    lg = linear_gaussian(2, q_std=0.3, r_std=0.5, num_steps=50)
    obs = jnp.asarray(linear_obs(lg, 0))

    def build_q(theta):
        q = jnp.array([[theta["a"], 0.02], [0.02, theta["b"]]])
        return LinearGaussian(lg.A, lg.H, 1.0, 0.5, lg.m0, lg.p0_std, lg.num_steps, lg.name, Q=q)

    def evidence(theta):
        return csf_jax.kalman_filter(obs, model=csf_jax.ParametricModel(build_q, theta)
                                     ).log_evidence.sum()

    theta = {"a": jnp.float64(0.09), "b": jnp.float64(0.12)}
    grad = jax.grad(evidence)(theta)
    fd = _central_differences(evidence, theta)
    for name in theta:
        assert float(grad[name]) == pytest.approx(fd[name], rel=0.01)


def test_enkf_gradient_with_fixed_keys_matches_finite_differences(x64, linear_obs):
    """The EnKF's draws are reparametrised: with the key fixed its evidence is a smooth function
    of theta, and ``jax.grad`` is that function's gradient."""
    obs = jnp.asarray(linear_obs(LG, 0))
    ensemble = to_model(LG).initial_ensemble(jax.random.key(1), 200).astype(jnp.float64)
    theta = _theta(jnp.float64)
    f = lambda t: _evidence(csf_jax.methods.enkf(), obs, ensemble, t)  # noqa: E731
    grad = jax.grad(f)(theta)
    fd = _central_differences(f, theta)
    for name in theta:
        assert float(grad[name]) == pytest.approx(fd[name], rel=0.01)


def test_particle_filter_gradient_is_near_the_exact_one(x64, linear_obs):
    """With the resampling's score carried, the particle filter's gradient is unbiased-looking:
    at N = 2000 the mean over 8 keys is within 20% of the Kalman filter's exact gradient
    (measured: within 1%) at a point where both noises are off by a factor of two. One run is
    noisy (measured relative std over keys: 22% for q, 3% for r on this record of K = 100);
    without the score (the resampled indices constants alone) q's gradient at the truth came
    out with the wrong sign."""
    obs = jnp.asarray(linear_obs(LG, 0))
    ensemble = to_model(LG).initial_ensemble(jax.random.key(1), 2000).astype(jnp.float64)
    theta = {"q": jnp.float64(0.15), "r": jnp.float64(0.8)}
    exact = jax.grad(lambda t: _kalman_evidence(obs, t))(theta)

    def grad(key):
        return jax.grad(lambda t: csf_jax.run(
            csf_jax.methods.pf(), obs, ensemble, model=csf_jax.ParametricModel(build, t),
            key=key, check_finite=False).log_evidence.sum())(theta)

    grads = jax.jit(jax.vmap(grad))(jax.random.split(jax.random.key(5), 8))
    for name in theta:
        assert float(grads[name].mean()) == pytest.approx(float(exact[name]), rel=0.2)


def _grid_mle(obs):
    """The exact maximum-likelihood (q, r) on a fine grid (Kalman filter, one compilation)."""
    q, r = jnp.meshgrid(jnp.linspace(0.1, 0.6, 101), jnp.linspace(0.2, 0.8, 121), indexing="ij")
    evidence = jax.jit(jax.vmap(lambda q, r: _kalman_evidence(obs, {"q": q, "r": r})))(
        q.ravel(), r.ravel())
    best = int(jnp.argmax(evidence))
    return float(q.ravel()[best]), float(r.ravel()[best])


def test_fit_recovers_the_linear_models_maximum_likelihood(x64, linear_obs):
    """From 500 steps, the Kalman fit and the EnKF fit land within 10% of the exact MLE of both
    noise levels (measured: within 1%), starting 50% off."""
    lg = LG._replace(num_steps=500)
    obs = jnp.asarray(linear_obs(lg, 3))
    q_hat, r_hat = _grid_mle(obs)
    start = {"q": 0.5, "r": 0.3}
    kalman = csf_jax.fit(build_lg, start, obs, None, key=jax.random.key(0),
                         method=csf_jax.methods.kalman(), steps=200,
                         transform=csf_jax.positive(), progress=False)
    ensemble = to_model(LG).initial_ensemble(jax.random.key(1), 100).astype(jnp.float64)
    enkf = csf_jax.fit(build, start, obs, ensemble, key=jax.random.key(0), steps=200,
                       transform=csf_jax.positive("q", "r"), progress=False)
    for result in (kalman, enkf):
        assert float(result.theta["q"]) == pytest.approx(q_hat, rel=0.1)
        assert float(result.theta["r"]) == pytest.approx(r_hat, rel=0.1)
        assert result.log_evidence.shape == (200,) and result.trace["q"].shape == (200,)
        assert float(result.log_evidence[-1]) > float(result.log_evidence[0])


def _pendulum(theta):
    return csf_jax.problems.get("pendulum")._replace(
        obs_noise=csf_jax.gaussian_noise(theta["r"]))


def test_fit_recovers_the_pendulums_observation_noise(capsys):
    """The EnKF fit of the pendulum's observation std from 200 steps is within 10% of the truth
    0.1 (measured 0.1002; the grid MLE of six records of 200 steps spread over 0.086 .. 0.110);
    progress lines go to stderr."""
    model = csf_jax.problems.get("pendulum")
    _, obs = csf_jax.simulate(model, jax.random.key(2), 200)
    ensemble = model.initial_ensemble(jax.random.key(3), 200)
    result = csf_jax.fit(_pendulum, {"r": 0.3}, obs, ensemble, key=jax.random.key(0), steps=100,
                         transform=csf_jax.positive(), progress=True)
    assert float(result.theta["r"]) == pytest.approx(0.1, rel=0.1)
    err = capsys.readouterr().err
    assert "fit: step 100/100: log evidence" in err and "r=" in err


def test_refusals(linear_obs):
    obs = jnp.asarray(linear_obs(LG, 0), jnp.float32)
    ensemble = to_model(LG).initial_ensemble(jax.random.key(1), 16)
    key = jax.random.key(0)
    with pytest.raises(TypeError, match="ParametricModel: build must be a callable"):
        csf_jax.ParametricModel(3.0, THETA)
    with pytest.raises(ValueError, match="obs_noise.gaussian_std must be a finite number > 0, "
                                         "got -0.5"):
        csf_jax.run(csf_jax.methods.enkf(), obs, ensemble, key=key,
                    model=csf_jax.ParametricModel(build, {"q": 0.3, "r": -0.5}))
    with pytest.raises(TypeError, match="build\\(theta\\) must return a LinearGaussian"):
        csf_jax.kalman_filter(obs, model=csf_jax.ParametricModel(build, THETA))
    with pytest.raises(TypeError, match="build\\(theta\\) must return a csf_jax.StateSpaceModel"):
        csf_jax.run(csf_jax.methods.enkf(), obs, ensemble, key=key,
                    model=csf_jax.ParametricModel(build_lg, THETA))
    with pytest.raises(TypeError, match="takes no csf_jax.ParametricModel"):
        csf_jax.run(csf_jax.methods.csf(), obs, ensemble, key=key,
                    model=csf_jax.ParametricModel(build, THETA))
    with pytest.raises(ValueError, match="fit: steps must be a positive int, got 0"):
        csf_jax.fit(build, THETA, obs, ensemble, key=key, steps=0)
    with pytest.raises(KeyError, match="theta has no entry 's'"):
        csf_jax.fit(build, THETA, obs, ensemble, key=key, steps=1,
                    transform=csf_jax.positive("s"))
