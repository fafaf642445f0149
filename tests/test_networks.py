"""Tests of the set encoder and the conditional score network.

Most tests share the particle count ``N`` so that the jitted helpers compile
only a handful of times.
"""

import dataclasses

import jax
import numpy as np
import pytest
from conftest import MATMUL_ATOL

from csf_jax import networks
from csf_jax.networks import NetworkConfig, ScoreNet, SetEncoder, init_params

# compared against closed forms at full float32 precision (on GPUs the default is TF32)
pytestmark = pytest.mark.usefixtures("highest_precision")

DIM = 3
N = 50
CONFIG = NetworkConfig()

encode = jax.jit(networks.encode, static_argnames="config")
score = jax.jit(networks.score, static_argnames="config")


def sigma_t(t, sigma_max=25.0):
    """Reference VE marginal std, written out independently of csf_jax.sde."""
    t = np.asarray(t, np.float64)
    return np.sqrt((sigma_max ** (2 * t) - 1) / (2 * np.log(sigma_max)))


def ensemble(n=N, seed=1, dim=DIM):
    """A non-centred float32 ensemble of shape (n, dim) (NumPy, so no eager JAX compiles)."""
    return (np.random.default_rng(seed).standard_normal((n, dim)) * 2.0 + 1.0).astype(np.float32)


@pytest.fixture(scope="module")
def params():
    return init_params(jax.random.key(0), CONFIG, DIM)


@pytest.fixture(scope="module")
def code(params):
    return encode(params, ensemble(), CONFIG)


def test_encoder_permutation_invariance(params, code):
    perm = np.random.default_rng(2).permutation(N)
    np.testing.assert_allclose(encode(params, ensemble()[perm], CONFIG), code,
                               atol=max(1e-5, MATMUL_ATOL))


def test_encoder_invariant_to_duplicating_the_set(params, code):
    doubled = np.concatenate([ensemble(), ensemble()])
    np.testing.assert_allclose(encode(params, doubled, CONFIG), code,
                               atol=max(1e-5, MATMUL_ATOL))


def test_seed_in_keys_breaks_size_independence(params):
    config = dataclasses.replace(CONFIG, pma_seed_in_keys=True)
    c = encode(params, ensemble(), config)
    c_doubled = encode(params, np.concatenate([ensemble(), ensemble()]), config)
    assert not np.allclose(c, c_doubled, atol=1e-5)


@pytest.mark.parametrize("n", [1, 7, 2 * N])
def test_encoder_shape_for_any_ensemble_size(params, n):
    c = encode(params, ensemble(n), CONFIG)
    assert c.shape == (CONFIG.code_dim,)
    assert np.all(np.isfinite(c))


def test_ensemble_features_use_population_variance():
    ens = ensemble(6)
    u = jax.jit(networks.ensemble_features)(ens)
    assert u.shape == (6, 3 * DIM)
    np.testing.assert_allclose(u[:, :DIM], ens)
    np.testing.assert_allclose(u[0, DIM : 2 * DIM], np.mean(ens, axis=0), atol=1e-6)
    np.testing.assert_allclose(u[3, 2 * DIM :], np.var(ens, axis=0, ddof=0), rtol=1e-5)


def test_score_shapes(params, code):
    x = ensemble(seed=4)
    assert score(params, x, 0.5, code, CONFIG).shape == (N, DIM)
    assert score(params, x[0], 0.5, code, CONFIG).shape == (DIM,)


def test_score_is_raw_output_over_sigma(params, code):
    x = ensemble(seed=4)
    t = np.linspace(0.01, 1.0, N, dtype=np.float32)
    apply = jax.jit(lambda p, x, t, c: ScoreNet(CONFIG).apply(p, x, t, c, capture_intermediates=True))
    s, state = apply(params["score"], x, t, code)
    raw = state["intermediates"]["out"]["__call__"][0]
    np.testing.assert_allclose(s, raw / sigma_t(t)[:, None], rtol=1e-5)
    assert np.all(np.isfinite(s * sigma_t(t)[:, None]))
    assert np.all(np.abs(raw) > 0)


def test_score_broadcasting_of_t_and_c(params, code):
    x = ensemble(seed=5)
    shared = score(params, x, 0.3, code, CONFIG)
    per_t = score(params, x, np.full((N,), 0.3, np.float32), code, CONFIG)
    per_c = score(params, x, 0.3, np.tile(code, (N, 1)), CONFIG)
    per_both = score(params, x, np.full((N,), 0.3, np.float32), np.tile(code, (N, 1)), CONFIG)
    for other in (per_t, per_c, per_both):
        np.testing.assert_allclose(other, shared, atol=1e-5)


def test_score_batch_equals_vmap_over_particles(params, code):
    x = ensemble(seed=6)
    batched = score(params, x, 0.7, code, CONFIG)
    mapped = jax.jit(jax.vmap(lambda xi: networks.score(params, xi, 0.7, code, CONFIG)))(x)
    np.testing.assert_allclose(batched, mapped, atol=1e-5)


def test_conditional_part_computed_once(params, code):
    cond_dim = 2 * CONFIG.fourier_features + CONFIG.code_dim
    jaxpr = jax.make_jaxpr(lambda x: networks.score(params, x, 0.7, code, CONFIG))(ensemble())
    dots = [e for e in jaxpr.jaxpr.eqns if e.primitive.name == "dot_general"]
    cond_shapes = [e.invars[0].aval.shape for e in dots if e.invars[0].aval.shape[-1] == cond_dim]
    assert cond_shapes == [(cond_dim,)]


def test_jit_and_vmap_over_ensembles(params):
    ensembles = np.stack([ensemble(seed=s) for s in (8, 9, 10)])

    def encode_and_score(ens):
        c = networks.encode(params, ens, CONFIG)
        return networks.score(params, ens, 0.5, c, CONFIG)

    vmapped = jax.jit(jax.vmap(encode_and_score))(ensembles)
    assert vmapped.shape == (3, N, DIM)
    single = score(params, ensembles[1], 0.5, encode(params, ensembles[1], CONFIG), CONFIG)
    np.testing.assert_allclose(vmapped[1], single, atol=1e-5)
    batched_codes = encode(params, ensembles, CONFIG)
    assert batched_codes.shape == (3, CONFIG.code_dim)
    np.testing.assert_allclose(batched_codes[2], encode(params, ensembles[2], CONFIG), atol=1e-5)


def test_init_params_structure():
    config = NetworkConfig(hidden=16, heads=2, blocks=1, code_dim=8, score_hidden=32, score_layers=2)
    shapes = jax.eval_shape(lambda key: init_params(key, config, dim=5, ensemble_size=4), jax.random.key(0))
    assert set(shapes) == {"encoder", "score"}
    assert shapes["encoder"]["params"]["pma_seed"].shape == (16,)
    assert shapes["encoder"]["params"]["head_out"]["kernel"].shape == (16, 8)
    assert shapes["score"]["params"]["out"]["kernel"].shape == (32, 5)
    assert shapes["score"]["params"]["cond_in"]["kernel"].shape == (2 * config.fourier_features + 8, 32)


def test_modules_are_hashable_by_config():
    assert hash(SetEncoder(CONFIG)) == hash(SetEncoder(NetworkConfig()))
    assert hash(ScoreNet(CONFIG)) == hash(ScoreNet(NetworkConfig()))


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"hidden": 30, "heads": 4}, "hidden"),
        ({"heads": 0}, "heads"),
        ({"blocks": -1}, "blocks"),
        ({"code_dim": 2.5}, "code_dim"),
        ({"score_layers": 0}, "score_layers"),
        ({"fourier_features": 0}, "fourier_features"),
        ({"sigma_max": 1.0}, "sigma_max"),
    ],
)
def test_config_validation(kwargs, field):
    with pytest.raises(ValueError, match=field):
        NetworkConfig(**kwargs)
