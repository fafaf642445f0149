"""Every filter runs on every named problem (short runs): PF, EnKF, and CSF with the exact
mixture prior and with randomly initialised networks."""

import jax
import jax.numpy as jnp
import pytest

import csf_jax
from csf_jax import CSFConfig, NetworkConfig, problems

SMALL_NET = NetworkConfig(hidden=16, heads=2, blocks=1, code_dim=8, score_hidden=32,
                          score_layers=2)


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
    params = csf_jax.init_params(jax.random.key(3), SMALL_NET, dim=model.dim)
    results["csf_random_net"] = csf_jax.filter(params, obs, ens, problem=model, key=key,
                                               network=SMALL_NET,
                                               config=CSFConfig(reverse_steps=50))
    for method, r in results.items():
        assert r.mean.shape == (4, model.dim), method
        assert bool(jnp.isfinite(r.mean).all()), method
