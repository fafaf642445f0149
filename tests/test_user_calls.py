"""The public calls as a user writes them: under ``jax.jit`` and ``jax.vmap``, with count data,
with lists, and with the argument mistakes a new user makes, each answered by a result or a
one-line error naming the argument and what to do."""

import functools
import inspect
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax import methods

K, N = 5, 50


@pytest.fixture(scope="module")
def data():
    """The double-well model, K steps of its observations and an N-member ensemble."""
    model = csf_jax.problems.get("double_well", num_steps=K, obs_std=0.5)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ensemble = model.initial_ensemble(jax.random.key(1), N)
    return model, obs, ensemble


@pytest.fixture(scope="module")
def counts():
    """The double-well model observed through Poisson counts, and float counts of it."""
    model = csf_jax.problems.get("double_well", num_steps=K)._replace(
        obs_noise=csf_jax.poisson_likelihood())
    _, obs = csf_jax.simulate(model, jax.random.key(2))
    return model, np.asarray(obs), model.initial_ensemble(jax.random.key(3), 50)


def _strict(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` with every warning an error."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return fn(*args, **kwargs)


def _close(a, b):
    np.testing.assert_allclose(np.asarray(a.mean), np.asarray(b.mean), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(a.std), np.asarray(b.std), rtol=1e-5, atol=1e-6)


# --- jax.jit and jax.vmap of the public calls -----------------------------------------------


@pytest.mark.parametrize("name", ["enkf", "pf", "run"])
def test_jit_of_a_public_call_equals_the_plain_call(data, name):
    model, obs, ens = data
    key = jax.random.key(4)
    call = {"enkf": csf_jax.ensemble_kalman_filter, "pf": csf_jax.particle_filter,
            "run": functools.partial(csf_jax.run, methods.enkf(inflation=1.02))}[name]
    got = _strict(jax.jit(call), obs, ens, model=model, key=key)
    _close(got, call(obs, ens, model=model, key=key))
    assert bool(got.finite.all())


def test_jit_of_csf_filter_equals_the_plain_call(data):
    model, obs, ens = data
    obs, ens, key, config = obs[:3], ens[:20], jax.random.key(5), csf_jax.CSFConfig()
    got = _strict(jax.jit(csf_jax.filter), None, obs, ens, model=model, key=key, config=config)
    _close(got, csf_jax.filter(None, obs, ens, model=model, key=key, config=config))


def test_vmap_over_runs_equals_the_runs_one_by_one(data):
    model, obs, ens = data
    obs_b = jnp.stack([obs, obs + 0.1])
    ens_b = jnp.stack([ens, ens[::-1]])
    keys = jax.random.split(jax.random.key(6), 2)
    got = _strict(jax.vmap(csf_jax.ensemble_kalman_filter), obs_b, ens_b, model=model, key=keys)
    assert got.mean.shape == (2, K, model.dim)
    for i in range(2):
        want = csf_jax.ensemble_kalman_filter(obs_b[i], ens_b[i], model=model, key=keys[i])
        _close(jax.tree_util.tree_map(lambda x, i=i: x[i], got), want)
    mapped = jax.vmap(lambda o, e, k: csf_jax.run(methods.pf(), o, e, model=model, key=k))
    assert mapped(obs_b, ens_b, keys).mean.shape == (2, K, model.dim)


@pytest.mark.parametrize("flag", ["return_ensembles", "check_finite"])
def test_a_traced_python_flag_is_refused_by_name(data, flag):
    model, obs, ens = data
    with pytest.raises(TypeError, match=rf"particle_filter: {flag} is traced .*"
                                        rf"static_argnames=\('{flag}',\)"):
        jax.jit(csf_jax.particle_filter)(obs, ens, model=model, key=jax.random.key(0),
                                         **{flag: True})


def test_flags_marked_static_or_bound_work_under_jit(data):
    model, obs, ens = data
    call = jax.jit(csf_jax.particle_filter, static_argnames=("return_ensembles",))
    got = call(obs, ens, model=model, key=jax.random.key(0), return_ensembles=True)
    assert got.ensembles.shape == (K, N, model.dim)
    seen = []
    bound = jax.jit(functools.partial(csf_jax.particle_filter, progress=seen.append))
    jax.block_until_ready(bound(obs, ens, model=model, key=jax.random.key(0)).mean)
    jax.effects_barrier()
    assert len(seen) == K


def test_models_and_settings_are_pytrees_without_leaves(data):
    model = data[0]
    assert jax.tree_util.tree_leaves(model) == []
    for cls in methods.STATIC_SETTINGS:
        default = cls() if cls not in (csf_jax.Localization, csf_jax.PriorScore) else None
        if default is not None:
            assert jax.tree_util.tree_leaves(default) == [], cls.__name__
    assert jax.tree_util.tree_leaves(csf_jax.ring_localization(4, [0, 2])) == []
    assert jax.tree_util.tree_leaves(csf_jax.gaussian_prior()) == []
    # every settings object a public filter takes by default passes jit as static
    plain = (bool, int, float, str, type(None))
    for name in csf_jax.__all__:
        fn = getattr(csf_jax, name)
        if not inspect.isfunction(fn) or "obs" not in inspect.signature(fn).parameters:
            continue
        for p in inspect.signature(fn).parameters.values():
            if p.default is p.empty or isinstance(p.default, plain) or callable(p.default):
                continue
            assert jax.tree_util.tree_leaves(p.default) == [], f"{name}({p.name}=...)"


# --- count data -----------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.int32, np.int64, "jax"])
@pytest.mark.parametrize("name", ["pf", "enkf"])
def test_integer_counts_filter_as_their_floats(counts, dtype, name):
    model, obs, ens = counts
    call = {"pf": csf_jax.particle_filter, "enkf": csf_jax.ensemble_kalman_filter}[name]
    ints = jnp.asarray(obs, jnp.int32) if dtype == "jax" else obs.astype(dtype)
    key = jax.random.key(7)
    got = _strict(call, ints, ens, model=model, key=key)
    want = call(obs, ens, model=model, key=key)
    np.testing.assert_array_equal(np.asarray(got.mean), np.asarray(want.mean))


def test_integer_obs_for_a_continuous_noise_say_to_pass_floats(data):
    model, obs, ens = data
    with pytest.raises(TypeError, match=r"ensemble_kalman_filter: obs must be a floating array, "
                                        r"got dtype int32; pass floats"):
        csf_jax.ensemble_kalman_filter(np.asarray(obs).astype(np.int32), ens, model=model,
                                       key=jax.random.key(0))


@pytest.mark.parametrize("bad, shown", [(-3.0, "-3"), (2.5, "2.5")])
def test_a_count_outside_the_support_is_refused_by_step_and_entry(counts, bad, shown):
    model, obs, ens = counts
    obs = obs.copy()
    obs[3, 0] = bad
    want = (rf"particle_filter: obs\[3, 0\] = {shown} is outside the support of the poisson "
            rf"likelihood \(non-negative integer counts\)")
    with pytest.raises(ValueError, match=want):
        csf_jax.particle_filter(obs, ens, model=model, key=jax.random.key(0))
    with pytest.raises(ValueError, match="outside the support"):
        csf_jax.run(methods.enkf(), obs.astype(np.int32) if bad < 0 else obs, ens, model=model,
                    key=jax.random.key(0))


def test_a_missing_count_is_not_outside_the_support(counts):
    model, obs, ens = counts
    obs = obs.copy()
    obs[2, 0] = np.nan
    got = _strict(csf_jax.particle_filter, obs, ens, model=model, key=jax.random.key(0))
    assert bool(got.finite.all())


# --- arrays given as lists ------------------------------------------------------------------


def test_lists_filter_as_arrays_without_a_warning(data):
    model, obs, ens = data
    key = jax.random.key(8)
    got = _strict(csf_jax.ensemble_kalman_filter, np.asarray(obs).tolist(),
                  np.asarray(ens).tolist(), model=model, key=key)
    _close(got, csf_jax.ensemble_kalman_filter(obs, ens, model=model, key=key))
    got = _strict(csf_jax.run, methods.enkf(), np.asarray(obs).tolist(), ens, model=model, key=key)
    assert bool(got.finite.all())


def test_a_ragged_list_is_refused_in_one_line(data):
    model, _, ens = data
    with pytest.raises(TypeError, match=r"particle_filter: obs must be a numeric array of shape "
                                        r"\(K, m\)"):
        csf_jax.particle_filter([[1.0], [2.0, 3.0]], ens, model=model, key=jax.random.key(0))


# --- argument mistakes ----------------------------------------------------------------------


@pytest.mark.parametrize("builder", ["enkf", "pf"])
def test_an_ensemble_filter_refuses_none_for_the_ensemble(data, builder):
    model, obs, _ = data
    with pytest.raises(TypeError, match=r"ensemble is None, but this filter needs an \(N, d\) "
                                        r"initial ensemble .* only the Kalman filter"):
        csf_jax.run(methods.build(builder), obs, None, model=model, key=jax.random.key(0))


@pytest.mark.parametrize("kernel", [None, "enkf"])
def test_method_refuses_what_is_not_a_kernel(kernel):
    with pytest.raises(TypeError, match=r"csf_jax.Method: kernel must be a .*Kernel, got .*; "
                                        r"make a Method with a builder, csf_jax.methods.enkf\(\), "
                                        r"or by name, csf_jax.methods.build\('enkf'\)"):
        csf_jax.Method(kernel)


def test_build_refuses_a_name_that_is_not_a_str_and_positional_settings():
    with pytest.raises(TypeError, match=r"methods.build: name must be a str, one of csf, enkf, "
                                        r".*; got \['enkf'\] \(list\)"):
        methods.build(["enkf"])
    with pytest.raises(TypeError, match=r"methods.build\('enkf'\): settings are keywords, got 1 "
                                        r"positional value\(s\); name them, e.g. "
                                        r"methods.build\('enkf', inflation=1.05\)"):
        methods.build("enkf", 1.05)
    with pytest.raises(TypeError, match=r"methods.build\('pf'\): settings are keywords"):
        methods.build("pf", 1)
    assert methods.build("enkf", inflation=1.05).name == "ensemble_kalman_filter"


@pytest.mark.parametrize("call, want", [
    (lambda o, e, m, k: csf_jax.run(methods.enkf(), o, e, m, key=k),
     r"csf_jax.run: takes 3 positional argument\(s\) \(method, obs, ensemble\), got 4; model= "
     r"and key= are keywords: csf_jax.run\(method, obs, ensemble, model=model, key=key\)"),
    (lambda o, e, m, k: csf_jax.filter(None, o, e, m, key=k),
     r"csf_jax.filter: takes 3 positional argument\(s\) \(params, obs, ensemble\), got 4"),
    (lambda o, e, m, k: csf_jax.ensemble_kalman_filter(o, e, m, k),
     r"ensemble_kalman_filter: takes 2 positional argument\(s\) \(obs, ensemble\), got 4; "
     r"model= and key= are keywords"),
    (lambda o, e, m, k: csf_jax.particle_filter(o, e, m, key=k),
     r"particle_filter: takes 2 positional argument\(s\)"),
])
def test_the_model_passed_positionally_is_refused_in_one_line(data, call, want):
    model, obs, ens = data
    with pytest.raises(TypeError, match=want):
        call(obs, ens, model, jax.random.key(0))
