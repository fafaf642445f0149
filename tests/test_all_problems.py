"""Every filter runs on every named problem (short runs): PF, EnKF, and CSF with the exact
mixture prior, with randomly initialised networks, and with the shipped pretrained model (the last
two share one compilation)."""

import jax
import jax.numpy as jnp
import pytest

import csf_jax
from csf_jax import CSFConfig, problems
from csf_jax.pretrained import MODEL_FOR, load_pretrained


def _data(name, n=32, k=4):
    model = problems.get(name, num_steps=k)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    return model, truth, obs, model.initial_ensemble(jax.random.key(1), n)


@pytest.mark.parametrize("name", problems.NAMES)
def test_every_filter_runs(name):
    model, truth, obs, ens = _data(name)
    key = jax.random.key(2)
    results = {
        "pf": csf_jax.particle_filter(obs, ens, problem=model, key=key),
        "enkf": csf_jax.ensemble_kalman_filter(obs, ens, problem=model, key=key),
        "csf_exact": csf_jax.filter(None, obs, ens, problem=model, key=key,
                                    config=CSFConfig(reverse_steps=50)),
    }
    shipped = load_pretrained(name)
    assert shipped.meta["problem"] == MODEL_FOR[name]
    random = csf_jax.init_params(jax.random.key(3), shipped.network, dim=model.dim)
    for label, params in (("csf_random_net", random), ("csf_pretrained", shipped.params)):
        results[label] = csf_jax.filter(params, obs, ens, problem=model, key=key,
                                        network=shipped.network,
                                        config=CSFConfig(reverse_steps=50))
    for method, r in results.items():
        assert r.mean.shape == (4, model.dim), method
        assert bool(jnp.isfinite(r.mean).all()), method
