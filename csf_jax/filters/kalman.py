"""The exact Kalman filter of a ``LinearGaussian`` model: the reference for the other filters.

Each step predicts with ``A`` and ``Q`` (``q_std^2 I`` unless the model gives a full ``Q``) and
updates on ``y_{k+1}`` with ``H`` and ``R`` (``r_std^2 I`` unless given), starting from
``N(m0, p0_std^2 I)`` at time 0. NaN entries of ``obs`` are missing: their rows of ``H`` and of the
innovation are zeroed and their rows and columns of ``R`` replaced by the identity's, which is the
exact update on the observed entries alone (a step with none is a pure forecast). The gain is computed with a
Cholesky solve of the innovation covariance, and the covariance update uses the Joseph form so it
stays symmetric positive semi-definite. Runs in float64 when ``jax_enable_x64`` is on and ``obs``
is float64; otherwise in the dtype of ``obs``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl

from csf_jax._checks import check_finite
from csf_jax.filters.result import FilterResult, mark_nonfinite
from csf_jax.problems.linear import LinearGaussian


def kalman_filter(obs, *, lg: LinearGaussian) -> FilterResult:
    """Filtered means and stds of ``x_1 .. x_K`` given ``obs (K, m) = y_1 .. y_K`` (NaN: missing).

    Returns ``FilterResult(mean (K, d), std (K, d), finite (K,))`` with
    ``std = sqrt(diag(P_{k|k}))``; no ensembles, no ESS. Use ``kalman_filter_cov`` for the full
    covariances.
    """
    means, covs = kalman_filter_cov(obs, lg)
    std = jnp.sqrt(jnp.clip(jnp.diagonal(covs, axis1=-2, axis2=-1), 0.0))
    return mark_nonfinite(FilterResult(mean=means, std=std), jnp.asarray(obs))


def kalman_filter_cov(obs, lg: LinearGaussian):
    """Filtered means ``(K, d)`` and covariances ``(K, d, d)`` of ``x_1 .. x_K``."""
    obs = jnp.asarray(obs)
    _check_obs(obs, lg)
    dtype = obs.dtype
    return _kalman_scan(obs, jnp.asarray(lg.A, dtype), jnp.asarray(lg.H, dtype),
                        jnp.asarray(lg.process_cov(), dtype), jnp.asarray(lg.obs_cov(), dtype),
                        jnp.asarray(lg.m0, dtype), jnp.asarray(lg.p0_std, dtype) ** 2)


def _check_obs(obs, lg: LinearGaussian) -> None:
    """``obs`` must be a floating ``(K, m)`` array with ``m = lg.obs_dim``, ``K >= 1`` and no inf
    (NaN: missing)."""
    if obs.ndim != 2:
        raise ValueError(f"kalman_filter: obs must have shape (K, m) = (steps, obs_dim), got "
                         f"{obs.shape}; use jax.vmap for batches of runs")
    if obs.shape[1] != lg.obs_dim:
        raise ValueError(f"kalman_filter: obs has dimension m={obs.shape[1]} but model "
                         f"{lg.name!r} has obs_dim={lg.obs_dim}")
    if obs.shape[0] < 1:
        raise ValueError(f"kalman_filter: obs must hold at least one step, got shape {obs.shape}")
    if not jnp.issubdtype(obs.dtype, jnp.floating):
        raise TypeError(f"kalman_filter: obs must be a floating array, got dtype {obs.dtype}")
    check_finite("kalman_filter: obs", obs, allow_nan=True)


@jax.jit
def _kalman_scan(obs, A, H, Q, R, m0, p0_var):
    """One ``lax.scan`` of predict/update steps. ``obs (K, m)``, ``A, Q (d, d)``, ``H (m, d)``,
    ``R (m, m)``."""
    d, m = A.shape[0], H.shape[0]
    eye_d, eye_m = jnp.eye(d, dtype=A.dtype), jnp.eye(m, dtype=A.dtype)

    def step(carry, y):
        mean, cov = carry
        mask = ~jnp.isnan(y)
        H_k = jnp.where(mask[:, None], H, 0.0)
        R_k = jnp.where(mask[:, None] & mask[None, :], R, eye_m)
        mean = A @ mean
        cov = A @ cov @ A.T + Q
        S = H_k @ cov @ H_k.T + R_k
        gain = jsl.cho_solve(jsl.cho_factor(S, lower=True), H_k @ cov).T
        mean = mean + gain @ jnp.where(mask, y - H @ mean, 0.0)
        J = eye_d - gain @ H_k
        cov = J @ cov @ J.T + gain @ R_k @ gain.T
        cov = 0.5 * (cov + cov.T)
        return (mean, cov), (mean, cov)

    _, (means, covs) = jax.lax.scan(step, (m0, p0_var * eye_d), obs)
    return means, covs
