"""Error metrics. The paper's RMSE (Eq. rmse) is the root of the mean over runs and steps of the
squared full-state error norm."""

from __future__ import annotations

import jax.numpy as jnp


def rmse(estimate, truth):
    """Paper's RMSE: ``sqrt(mean_{runs, steps} ||x_hat - x||^2)``.

    Args:
      estimate: (..., K, d) with any leading run axes.
      truth: the same shape, already aligned with the estimate (pass ``truth[..., 1:, :]`` for a
        ``simulate()`` trajectory, which includes x_0).
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


def wasserstein_1d(a, b, num_quantiles: int = 512):
    """1-D Wasserstein-1 distance per coordinate between samples ``a (n, d)`` and ``b (m, d)``.

    ``W1 = int_0^1 |F_a^-1(u) - F_b^-1(u)| du``, on a midpoint grid of ``num_quantiles`` levels.
    Returns ``(d,)``.
    """
    u = (jnp.arange(num_quantiles) + 0.5) / num_quantiles
    qa = jnp.quantile(jnp.asarray(a), u, axis=0)
    qb = jnp.quantile(jnp.asarray(b), u, axis=0)
    return jnp.mean(jnp.abs(qa - qb), axis=0)
