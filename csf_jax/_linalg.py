"""Small dense linear algebra in plain jax.numpy, for the per-particle (d, d) systems of the Kalman
guidance.

Cholesky factorisation and triangular solves, vectorised over leading batch axes. They replace the
LAPACK custom calls of ``jnp.linalg.cholesky`` and ``jax.scipy.linalg.solve_triangular`` inside
the sampler's scans, which deadlocked XLA's CPU runtime under jax 0.10.2 (every worker thread
asleep and the result never ready, with ``--xla_cpu_enable_concurrency_optimized_scheduler`` on
and off; gone with these functions; the reproduction is on docs/design.md).

Each is a ``lax.fori_loop`` over columns (entries, for the solves), whose program, and so compile
time, is the same for every d. Unrolled in Python the program grows with d and its compile time
faster than d^2: at d = 20 the filter step compiled in over a minute with the columns unrolled
and is no faster per step (docs/bench/history.md, "Compile time against d").
"""


from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

PRECISION = "highest"


def precise(fn):
    """Decorator: ``fn``'s matrix products are traced at ``PRECISION`` ("highest": full float32).

    On GPUs, float32 matmuls default to TF32 (a 10-bit mantissa), too coarse for what this wraps:
    Cholesky factors, Kalman gains, covariances and the ensemble's Gaussian, whose errors the
    filters compound step after step. The score network keeps the default. On CPUs the two
    precisions are the same arithmetic.
    """

    @functools.wraps(fn)
    def inner(*args, **kwargs):
        with jax.default_matmul_precision(PRECISION):
            return fn(*args, **kwargs)

    return inner


@precise
def cholesky(a):
    """Lower Cholesky factor ``l`` with ``l l^T = a``; ``a: (..., d, d)`` symmetric positive definite.

    Column j: ``l[:, j] = (a[:, j] - l l[j, :]) / pivot`` on and below the diagonal, with the
    columns after j still zero.
    """
    d = a.shape[-1]
    below = jnp.arange(d)

    def column(j, l):
        row = lax.dynamic_index_in_dim(l, j, axis=-2, keepdims=False)  # (..., d): l[j, :j], zeros
        col = lax.dynamic_index_in_dim(a, j, axis=-1, keepdims=False) \
            - jnp.einsum("...ik,...k->...i", l, row)
        pivot = jnp.sqrt(lax.dynamic_index_in_dim(col, j, axis=-1, keepdims=False))
        col = jnp.where(below >= j, col / pivot[..., None], 0.0)
        return lax.dynamic_update_index_in_dim(l, col[..., None], j, axis=-1)

    return lax.fori_loop(0, d, column, jnp.zeros_like(a))


@precise
def solve_lower(l, b):
    """``x`` with ``l x = b``; ``l: (..., d, d)`` lower triangular, ``b: (..., d)``."""
    return _substitute(l, b, transposed=False)


@precise
def solve_lower_transposed(l, b):
    """``x`` with ``l^T x = b``; ``l: (..., d, d)`` lower triangular, ``b: (..., d)``."""
    return _substitute(l, b, transposed=True)


@precise
def cho_solve(l, b):
    """``x`` with ``l l^T x = b``."""
    return solve_lower_transposed(l, solve_lower(l, b))


def _substitute(l, b, transposed: bool):
    """Forward substitution ``l x = b`` (back substitution ``l^T x = b`` if ``transposed``), one
    entry of ``x`` per step, the entries not yet solved still zero."""
    d = l.shape[-1]
    b = jnp.broadcast_to(b, jnp.broadcast_shapes(b.shape, l.shape[:-1]))

    def entry(i, x):
        j = d - 1 - i if transposed else i
        coef = lax.dynamic_index_in_dim(l, j, axis=-1 if transposed else -2, keepdims=False)
        diag = lax.dynamic_index_in_dim(coef, j, axis=-1, keepdims=False)
        rhs = lax.dynamic_index_in_dim(b, j, axis=-1, keepdims=False)
        xj = (rhs - jnp.sum(coef * x, -1)) / diag
        return lax.dynamic_update_index_in_dim(x, xj[..., None], j, axis=-1)

    return lax.fori_loop(0, d, entry, jnp.zeros_like(b))


