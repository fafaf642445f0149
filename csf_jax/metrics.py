"""Error metrics. The paper's RMSE (Eq. rmse) is the root of the mean over runs and steps of the
squared full-state error norm."""

from __future__ import annotations

import jax.numpy as jnp


def rmse(estimate, truth):
    """Paper's RMSE: ``sqrt(mean_{runs, steps} ||x_hat - x||^2)``.

    estimate, truth: (..., K, d) with any leading run axes; truth must already be aligned with the
    estimate (pass ``truth[..., 1:, :]`` for a simulate() trajectory, which includes x_0).
    """
    estimate, truth = jnp.asarray(estimate), jnp.asarray(truth)
    if estimate.shape != truth.shape:
        raise ValueError(f"rmse: estimate {estimate.shape} and truth {truth.shape} differ in shape")
    return jnp.sqrt(jnp.mean(jnp.sum((estimate - truth) ** 2, axis=-1)))


def rmse_per_dim(estimate, truth):
    """The RMSE per coordinate, averaged over coordinates: ``rmse / sqrt(d)``-like, as a scalar
    ``sqrt(mean_{runs, steps, coords} (x_hat - x)^2)``."""
    estimate, truth = jnp.asarray(estimate), jnp.asarray(truth)
    if estimate.shape != truth.shape:
        raise ValueError(f"rmse_per_dim: estimate {estimate.shape} and truth {truth.shape} differ")
    return jnp.sqrt(jnp.mean((estimate - truth) ** 2))


def rmse_over_time(estimate, truth):
    """RMSE at each step, over runs: ``(..., K, d) -> (K,)``."""
    err = jnp.sum((jnp.asarray(estimate) - jnp.asarray(truth)) ** 2, axis=-1)
    return jnp.sqrt(jnp.mean(err.reshape(-1, err.shape[-1]), axis=0))
