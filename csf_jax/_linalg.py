"""Small dense linear algebra in plain jax.numpy, for the per-particle (d, d) systems of the Kalman
guidance.

Cholesky factorisation and triangular solves written as d unrolled column steps, vectorised over
leading batch axes. They replace the LAPACK custom calls of ``jnp.linalg.cholesky`` and
``jax.scipy.linalg.solve_triangular`` inside the sampler's scans, which deadlocked XLA's CPU runtime
(jax 0.10.2, 2-core CPU: vmapped over 16 runs of 1000 particles, every worker thread asleep and the
result never ready; reproduced with ``--xla_cpu_enable_concurrency_optimized_scheduler`` on and
off, gone with these functions). For d <= ~50 they cost about the same. Compile time grows with d (d steps are unrolled).
"""

from __future__ import annotations

import jax.numpy as jnp


def cholesky(a):
    """Lower Cholesky factor ``l`` with ``l l^T = a``; ``a: (..., d, d)`` symmetric positive definite."""
    d = a.shape[-1]
    cols = []
    for j in range(d):
        prev = jnp.stack(cols, -1) if cols else jnp.zeros(a.shape[:-1] + (0,), a.dtype)  # (..., d, j)
        col = a[..., :, j] - jnp.einsum("...ik,...k->...i", prev, prev[..., j, :])
        pivot = jnp.sqrt(col[..., j])
        col = jnp.where(jnp.arange(d) >= j, col / pivot[..., None], 0.0)
        cols.append(col)
    return jnp.stack(cols, -1)


def solve_lower(l, b):
    """``x`` with ``l x = b``; ``l: (..., d, d)`` lower triangular, ``b: (..., d)``."""
    d = l.shape[-1]
    xs = []
    for j in range(d):
        acc = b[..., j] - sum(l[..., j, k] * xs[k] for k in range(j)) if j else b[..., j]
        xs.append(acc / l[..., j, j])
    return jnp.stack(xs, -1)


def solve_lower_transposed(l, b):
    """``x`` with ``l^T x = b``; ``l: (..., d, d)`` lower triangular, ``b: (..., d)``."""
    d = l.shape[-1]
    xs = [None] * d
    for j in reversed(range(d)):
        acc = b[..., j] - sum(l[..., k, j] * xs[k] for k in range(j + 1, d)) if j < d - 1 \
            else b[..., j]
        xs[j] = acc / l[..., j, j]
    return jnp.stack(xs, -1)


def cho_solve(l, b):
    """``x`` with ``l l^T x = b``."""
    return solve_lower_transposed(l, solve_lower(l, b))
