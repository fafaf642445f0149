"""``normal``: ``jax.random.normal``'s draws, bit for bit, computed faster on a CPU.

The filters draw most of their randomness as standard normals: the sampler's K candidates per
member and level, the particle components' importance draws, the process noise. On a CPU,
``jax.random.normal`` can cost a level more than its linear algebra, for two reasons:

* its Threefry-2x32 hash is lowered on a CPU as a rolled loop of five iterations, each writing
  its two (n,) words to memory, where the unrolled rounds are one fused elementwise loop;
* its ``erf_inv`` fuses ``log1p`` with the two polynomials and the select into one loop that the
  compiler does not vectorise, where ``log1p`` in a loop of its own (here: a two-iteration
  ``lax.map``, which no fusion crosses) leaves the rest vectorised.

``normal`` computes the same function with those two changes: the bits of
``jax.random.bits`` under ``jax_threefry_partitionable`` (the Threefry-2x32 of the key and the
element's 64-bit index, its two words xor-ed), mapped to ``[nextafter(-1, 0), 1)`` as
``jax.random.uniform`` does, and ``sqrt(2) erf_inv(u)`` by the same single-precision polynomials
(Giles 2010) and operations as XLA's. The draws are identical to ``jax.random.normal``'s, bit for
bit (``tests/test_random.py``: many keys and shapes, under ``jit`` and ``vmap``), so a filter's
numbers do not change; only their cost does. Where the identity is not
established (not a CPU, another key implementation or bit layout, another dtype than float32),
``normal`` is ``jax.random.normal`` itself.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))
_PARITY = np.uint32(0x1BD11BDA)
_ERF_INV_CENTRAL = (2.81022636e-08, 3.43273939e-07, -3.5233877e-06, -4.39150654e-06,
                    0.00021858087, -0.00125372503, -0.00417768164, 0.246640727, 1.50140941)
_ERF_INV_TAIL = (-0.000200214257, 0.000100950558, 0.00134934322, -0.00367342844, 0.00573950773,
                 -0.0076224613, 0.00943887047, 1.00167406, 2.83297682)


def fast_path(key, shape, dtype) -> bool:
    """Whether ``normal`` computes the draws itself: a CPU, a Threefry-2x32 key, the
    partitionable bit layout, float32 and a non-empty shape of fewer than 2^32 elements."""
    if jax.default_backend() != "cpu" or np.dtype(dtype) != np.float32:
        return False
    if not jax.config.jax_threefry_partitionable:
        return False
    size = math.prod(shape)
    if not 0 < size < 2 ** 32:
        return False
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return key.shape == () and str(jax.random.key_impl(key)) == "threefry2x32"
    return key.dtype == jnp.uint32 and key.shape == (2,) \
        and jax.config.jax_default_prng_impl == "threefry2x32"


def _rotate_left(x, r: int):
    return lax.shift_left(x, np.uint32(r)) | lax.shift_right_logical(x, np.uint32(32 - r))


def threefry_2x32(k0, k1, x0, x1):
    """The Threefry-2x32 hash (20 rounds) of the counter words ``x0, x1`` under the key words
    ``k0, k1``, its rounds unrolled into one elementwise computation (uint32 arithmetic: exact)."""
    keys = (k0, k1, k0 ^ k1 ^ _PARITY)
    x0, x1 = x0 + keys[0], x1 + keys[1]
    for i in range(5):
        for r in _ROTATIONS[i % 2]:
            x0 = x0 + x1
            x1 = x0 ^ _rotate_left(x1, r)
        x0 = x0 + keys[(i + 1) % 3]
        x1 = x1 + keys[(i + 2) % 3] + np.uint32(i + 1)
    return x0, x1


def bits(key, shape):
    """``jax.random.bits(key, shape)`` (uint32) under the partitionable layout: the hash of each
    element's row-major index (high word 0 below 2^32 elements), its two output words xor-ed."""
    data = jax.random.key_data(key) if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else key
    index = lax.iota(np.uint32, math.prod(shape)).reshape(shape)
    out0, out1 = threefry_2x32(data[0], data[1], jnp.zeros(shape, np.uint32), index)
    return out0 ^ out1


def uniform_signed(key, shape):
    """``jax.random.uniform(key, shape, float32, nextafter(-1, 0), 1)``: 23 random mantissa bits
    under the exponent of 1, shifted and scaled."""
    low = np.nextafter(np.float32(-1.0), np.float32(0.0))
    mantissa = lax.shift_right_logical(bits(key, shape), np.uint32(32 - 23))
    one = lax.bitcast_convert_type(
        mantissa | np.array(1.0, np.float32).view(np.uint32), jnp.float32) - np.float32(1.0)
    return lax.max(low, one * (np.float32(1.0) - low) + low)


def _minus_log1p_minus_square(u):
    """``-log1p(-u^2)`` in a loop of its own (module docstring): a ``lax.map`` over two halves."""
    flat = u.reshape(-1)
    n = flat.shape[0]
    flat = jnp.pad(flat, (0, n % 2)).reshape(2, -1)
    return lax.map(lambda v: -jnp.log1p(-v * v), flat).reshape(-1)[:n].reshape(u.shape)


def erf_inv(u):
    """``lax.erf_inv`` of float32 ``u``, by the same operations as XLA's (Giles' two
    polynomials in ``w = -log1p(-u^2)``, the central one for ``w < 5``)."""
    w = _minus_log1p_minus_square(u)
    central, tail = w - np.float32(2.5), jnp.sqrt(w) - np.float32(3.0)
    p, q = np.float32(_ERF_INV_CENTRAL[0]), np.float32(_ERF_INV_TAIL[0])
    for a, b in zip(_ERF_INV_CENTRAL[1:], _ERF_INV_TAIL[1:]):
        p, q = np.float32(a) + p * central, np.float32(b) + q * tail
    return jnp.where(jnp.abs(u) == 1.0, jnp.inf * u, jnp.where(w < 5.0, p, q) * u)


def normal(key, shape=(), dtype=None):
    """``jax.random.normal(key, shape, dtype)``, bit for bit; faster on a CPU (module docstring).

    key: a ``jax.random.key`` (or a raw uint32 key of the default implementation).
    shape: the draws' shape.  dtype: their float dtype (None: JAX's default float, as there).
    """
    shape = tuple(int(s) for s in (shape if isinstance(shape, (tuple, list)) else (shape,)))
    dtype = jax.dtypes.canonicalize_dtype(float if dtype is None else dtype)
    if not fast_path(key, shape, dtype):
        return jax.random.normal(key, shape, dtype)
    return _fast_normal(key, shape)


@functools.partial(jax.jit, static_argnums=1)
def _fast_normal(key, shape):
    # one compiled computation, as jax.random.normal's own: called eagerly, op by op, the
    # uniform's multiply-add would round apart from its fused (contracted) form
    return np.float32(np.sqrt(2.0)) * erf_inv(uniform_signed(key, shape))
