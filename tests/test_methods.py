"""One way to call a filter: every builder of ``csf_jax.methods.REGISTRY`` makes a ``Method`` that
``csf_jax.run`` runs; a ``Method`` is a pytree of its params, so it goes through ``jax.jit`` and
``jax.vmap``; the named functions are conveniences over exactly this; the old keyword and flat
config names still work for one version, with a warning."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax import CSFConfig, InflationConfig, PriorConfig, SamplerConfig, methods, problems
from csf_jax.problems.linear import linear_gaussian, to_model

KEY = jax.random.key(2)
LG = linear_gaussian(2, 2, num_steps=4)
LINEAR = to_model(LG)
RING = problems.get("lorenz96", dim=8, num_steps=3, burn_in=0)
LOC = csf_jax.ring_localization(8, range(8))
FAST_CSF = CSFConfig(sampler=SamplerConfig(reverse_steps=3))


def _data(model, n=16):
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    return truth, obs, model.initial_ensemble(jax.random.key(1), n)


SETTINGS = {  # name: (model, builder settings)
    "csf": (LINEAR, {"config": FAST_CSF}),
    "enkf": (LINEAR, {"inflation": 1.1}),
    "pf": (LINEAR, {}),
    "letkf": (RING, {"localization": LOC}),
    "sharded_letkf": (RING, {"localization": LOC, "config": csf_jax.LETKFConfig(radius=2.0)}),
    "local_csf": (problems.get("lorenz96", dim=20, num_steps=3, burn_in=0),
                  {"localization": csf_jax.ring_localization(20, range(20)),
                   "config": csf_jax.LocalCSFConfig(half_width=2, block=5)}),
    "local_transform": (RING, {"localization": LOC}),
    "sharded_transform": (RING, {"localization": LOC,
                                 "config": csf_jax.LocalTransformConfig(radius=2.0)}),
    "ensf": (LINEAR, {"config": csf_jax.ENSFConfig(reverse_steps=5)}),
    "ienks": (RING, {"localization": LOC, "config": csf_jax.IEnKSConfig(adaptive=2.0)}),
    "sf": (LINEAR, {"config": csf_jax.SFConfig(train_steps=2, warmup_steps=2),
                    "sampler": FAST_CSF}),
    "reference": (problems.get("double_well", num_steps=4),
                  {"config": csf_jax.ReferenceConfig(particles=200, shock_draws=16)}),
    "kalman": (LINEAR, {}),
}


def test_every_registered_filter_has_settings_here():
    assert set(SETTINGS) == set(methods.REGISTRY)


@pytest.mark.parametrize("name", list(SETTINGS))
def test_every_registered_filter_runs_through_run(name):
    model, settings = SETTINGS[name]
    truth, obs, ens = _data(model)
    method = methods.build(name, **settings)
    assert isinstance(method, csf_jax.Method) and method.name
    result = csf_jax.run(method, obs, None if name == "kalman" else ens, model=model, key=KEY)
    assert result.mean.shape == truth[1:].shape and bool(result.finite.all())
    again = csf_jax.run(method, obs, None if name == "kalman" else ens, model=model, key=KEY)
    np.testing.assert_array_equal(result.mean, again.mean)  # same key, same result


def test_a_method_is_a_pytree_of_its_params_under_jit_and_vmap():
    truth, obs, ens = _data(LINEAR)
    method = methods.enkf(1.1)
    assert [np.asarray(x) for x in jax.tree_util.tree_leaves(method)] == [np.float32(1.1)]
    run = lambda m, o, e, k: csf_jax.run(m, o, e, model=LINEAR, key=k).mean
    np.testing.assert_allclose(jax.jit(run)(method, obs, ens, KEY), run(method, obs, ens, KEY),
                               rtol=1e-5, atol=1e-6)
    sweep = jax.vmap(lambda i: run(methods.enkf(i), obs, ens, KEY))(jnp.array([1.0, 1.1]))
    np.testing.assert_allclose(sweep[1], run(method, obs, ens, KEY), rtol=1e-5, atol=1e-6)


def test_named_filters_are_the_methods():
    truth, obs, ens = _data(LINEAR)
    named = csf_jax.ensemble_kalman_filter(obs, ens, model=LINEAR, key=KEY, inflation=1.1)
    built = csf_jax.run(methods.enkf(1.1), obs, ens, model=LINEAR, key=KEY)
    np.testing.assert_array_equal(named.mean, built.mean)
    named = csf_jax.filter(None, obs, ens, model=LINEAR, key=KEY, config=FAST_CSF)
    built = csf_jax.run(methods.csf(config=FAST_CSF), obs, ens, model=LINEAR, key=KEY)
    np.testing.assert_array_equal(named.mean, built.mean)


def test_bad_methods_and_settings_are_one_line_errors():
    truth, obs, ens = _data(LINEAR)
    with pytest.raises(TypeError, match="csf_jax.run: method must be a csf_jax.Method"):
        csf_jax.run(csf_jax.particle_filter, obs, ens, model=LINEAR, key=KEY)
    with pytest.raises(ValueError, match="unknown filter 'kalmann'; choose from csf, enkf"):
        methods.build("kalmann")
    with pytest.raises(TypeError, match=r"methods.build\('enkf'\): unknown setting\(s\) radius; "
                                        r"methods.enkf takes inflation"):
        methods.build("enkf", radius=3)
    with pytest.raises(TypeError, match="letkf: needs localization=.*ring_localization"):
        csf_jax.letkf(obs, ens, model=RING, key=KEY)
    with pytest.raises(TypeError, match="local_transform_filter: config must be a "
                                        "LocalTransformConfig, got LETKFConfig"):
        methods.local_transform(LOC, csf_jax.LETKFConfig())
    with pytest.raises(TypeError, match="config must be a CSFConfig"):
        methods.csf(config=SamplerConfig())


def test_the_old_model_keyword_warns_and_works():
    truth, obs, ens = _data(LINEAR)
    with pytest.warns(DeprecationWarning, match=r"particle_filter\(problem=...\) is now "
                                                r"particle_filter\(model=...\)"):
        old = csf_jax.particle_filter(obs, ens, problem=LINEAR, key=KEY)
    np.testing.assert_array_equal(old.mean, csf_jax.particle_filter(obs, ens, model=LINEAR,
                                                                    key=KEY).mean)
    with pytest.warns(DeprecationWarning, match="kalman_filter"):
        csf_jax.kalman_filter(obs, lg=LG)
    with pytest.raises(TypeError, match="got both problem= and model="):
        csf_jax.particle_filter(obs, ens, problem=LINEAR, model=LINEAR, key=KEY)


def test_flat_csf_config_fields_warn_and_map_to_their_groups():
    with pytest.warns(DeprecationWarning, match="CSFConfig.reverse_steps is "
                                                "CSFConfig.sampler.reverse_steps"):
        old = CSFConfig(reverse_steps=5, adaptive_inflation=False, mixture=csf_jax.MixtureConfig())
    assert old == CSFConfig(sampler=SamplerConfig(reverse_steps=5),
                            inflation=InflationConfig(adaptive=False),
                            prior=PriorConfig(mixture=csf_jax.MixtureConfig()))
    with pytest.warns(DeprecationWarning):
        assert old.reverse_steps == 5
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert old.sampler.reverse_steps == 5 and hash(old) == hash(CSFConfig(
            sampler=SamplerConfig(reverse_steps=5), inflation=InflationConfig(adaptive=False),
            prior=PriorConfig(mixture=csf_jax.MixtureConfig())))
    with pytest.raises(TypeError, match="unknown field.*reverse_step\\b"):
        CSFConfig(reverse_step=5)
    with pytest.raises(ValueError, match="SamplerConfig.reverse_steps must be >= 2"):
        SamplerConfig(reverse_steps=1)
    with pytest.raises(ValueError, match="InflationConfig.statistic must be one of"):
        InflationConfig(statistic="mean")


@pytest.mark.parametrize("name", [pytest.param(n, marks=[] if n in ("pf", "enkf") else
                                               pytest.mark.slow)  # each compiles twice
                                  for n in SETTINGS if not n.startswith("sharded") and n != "csf"])
def test_vmap_over_runs_gives_each_runs_own_call(name):
    """``jax.vmap`` over (obs, ensemble, key) gives what separate calls with the same keys give:
    bit for bit for the filters with discrete choices (run one at a time under the vmap), to
    float rounding for the smooth ones (batched). The sharded filters take concrete arrays only:
    they refuse a vmap; CSF's default has its own test below."""
    model, settings = SETTINGS[name]
    method = methods.build(name, **settings)
    keys = jax.random.split(jax.random.key(5), 3)
    obs = jax.vmap(lambda k: csf_jax.simulate(model, k)[1])(keys)
    ens = None if name == "kalman" else jax.vmap(lambda k: model.initial_ensemble(k, 16))(keys)
    run = lambda o, e, k: csf_jax.run(method, o, e, model=model, key=k).mean
    batched = jax.vmap(run)(obs, ens, keys)
    for i in range(3):
        alone = run(obs[i], None if ens is None else ens[i], keys[i])
        if method.kernel.discrete:
            np.testing.assert_array_equal(batched[i], alone)
        else:
            np.testing.assert_allclose(batched[i], alone, rtol=1e-5, atol=1e-5)


def test_vmapped_csf_runs_do_not_part_from_their_own_calls():
    """The default CSF over 15 steps of the double well (N = 200, 3 runs): batched, the runs
    differ from their separate calls by rounding, which a flipped choice (a resampled member, a
    line search's pick) turns into 1e-3 over 30 steps; run one at a time under the vmap they
    agree bit for bit."""
    model = problems.get("double_well", num_steps=15)
    keys = jax.random.split(jax.random.key(11), 3)
    obs = jax.vmap(lambda k: csf_jax.simulate(model, k)[1])(keys)
    ens = jax.vmap(lambda k: model.initial_ensemble(k, 200))(keys)
    run = lambda o, e, k: csf_jax.filter(None, o, e, model=model, key=k).mean
    batched = jax.vmap(run)(obs, ens, keys)
    for i in range(3):
        np.testing.assert_array_equal(batched[i], run(obs[i], ens[i], keys[i]))


def test_gradients_go_through_a_vmapped_run():
    """A smooth filter stays batched and differentiable under ``jax.vmap``: the EnKF's gradient
    in its initial ensemble, taken of a sum over a vmap of two ensembles, is each run's own."""
    truth, obs, ens = _data(LINEAR)
    two = jnp.stack([ens, ens[::-1] + 0.1])
    loss = lambda e: csf_jax.run(methods.enkf(), obs, e, model=LINEAR, key=KEY).mean.sum()
    alone = [jax.grad(loss)(e) for e in two]
    assert float(jnp.abs(alone[0]).sum()) > 0
    grads = jax.grad(lambda es: jax.vmap(loss)(es).sum())(two)
    for i in range(2):
        np.testing.assert_allclose(grads[i], alone[i], rtol=1e-5, atol=1e-6)
