"""``csf_jax._random.normal`` draws what ``jax.random.normal`` draws, bit for bit: the filters'
numbers do not depend on which of the two computed them."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from csf_jax import _random

SHAPES = [(), (1,), (2, 3), (7,), (1000, 20), (8, 1000, 10), (64, 20), (3, 5, 1), (4097,)]


@pytest.mark.parametrize("shape", SHAPES)
def test_normal_equals_jax_random_normal_bit_for_bit(shape):
    for seed in range(12):
        key = jax.random.fold_in(jax.random.key(seed), 7)
        want = np.asarray(jax.random.normal(key, shape))
        got = np.asarray(jax.jit(lambda k: _random.normal(k, shape))(key))
        assert got.dtype == want.dtype and got.shape == want.shape
        np.testing.assert_array_equal(got, want)


def test_normal_fast_path_is_taken_on_a_cpu_and_its_bits_are_jaxs():
    key = jax.random.key(3)
    if jax.default_backend() == "cpu":
        assert _random.fast_path(key, (5, 4), jnp.float32)
    np.testing.assert_array_equal(np.asarray(jax.jit(lambda k: _random.bits(k, (9, 4)))(key)),
                                  np.asarray(jax.random.bits(key, (9, 4))))
    np.testing.assert_array_equal(np.asarray(jax.jit(lambda k: _random.uniform_signed(k, (50,)))(key)),
                                  np.asarray(jax.random.uniform(
                                      key, (50,), jnp.float32,
                                      np.nextafter(np.float32(-1), np.float32(0)), 1.0)))


def test_erf_inv_equals_lax_erf_inv_across_its_domain():
    # both polynomial branches (w < 5 and the tail near +-1) and the end points
    u = np.concatenate([np.linspace(-1, 1, 200_001, dtype=np.float32),
                        1 - np.logspace(-8, -1, 5000, dtype=np.float32),
                        -1 + np.logspace(-8, -1, 5000, dtype=np.float32)])
    np.testing.assert_array_equal(np.asarray(jax.jit(_random.erf_inv)(u)),
                                  np.asarray(jax.jit(jax.lax.erf_inv)(u)))


def test_normal_under_vmap_and_in_a_scan_equals_jax():
    keys = jax.random.split(jax.random.key(5), 4)
    want = jax.vmap(lambda k: jax.random.normal(k, (100, 3)))(keys)
    got = jax.jit(jax.vmap(lambda k: _random.normal(k, (100, 3))))(keys)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))

    def body(c, k):
        return c + _random.normal(k, (6, 2)).sum(), _random.normal(k, (6, 2))

    _, got = jax.lax.scan(body, 0.0, keys)
    np.testing.assert_array_equal(np.asarray(got),
                                  np.asarray(jax.vmap(lambda k: jax.random.normal(k, (6, 2)))(keys)))


def test_normal_with_a_raw_key_and_with_other_dtypes_and_implementations():
    raw = jax.random.PRNGKey(11)
    np.testing.assert_array_equal(np.asarray(_random.normal(raw, (30,))),
                                  np.asarray(jax.random.normal(raw, (30,))))
    # not the fast path: handed to jax.random.normal itself
    rbg = jax.random.key(1, impl="rbg")
    assert not _random.fast_path(rbg, (30,), jnp.float32)
    np.testing.assert_array_equal(np.asarray(_random.normal(rbg, (30,))),
                                  np.asarray(jax.random.normal(rbg, (30,))))
    assert not _random.fast_path(jax.random.key(1), (30,), jnp.float16)
    half = _random.normal(jax.random.key(1), (30,), jnp.float16)
    assert half.dtype == jnp.float16
    np.testing.assert_array_equal(np.asarray(half),
                                  np.asarray(jax.random.normal(jax.random.key(1), (30,), jnp.float16)))
    assert not _random.fast_path(jax.random.key(1), (0,), jnp.float32)
    assert _random.normal(jax.random.key(1), (0, 3)).shape == (0, 3)


def test_the_draws_are_standard_normal():
    # a test that can fail: the moments and the tails of 10^6 draws
    z = np.asarray(_random.normal(jax.random.key(0), (1_000_000,)))
    assert abs(z.mean()) < 0.005 and abs(z.std() - 1.0) < 0.005
    assert abs((np.abs(z) > 3).mean() - 0.0027) < 0.0005
