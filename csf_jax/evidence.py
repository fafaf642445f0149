"""The data's likelihood, one step at a time: ``log p(y_k | y_1 .. y_{k-1})``.

Every filter that can estimates it from what its update already computes, and returns it as
``FilterResult.log_evidence (K,)``; the sum over steps is the log-likelihood of the whole record,
``log p(y_1 .. y_K)``, which fits a model's parameters (``csf_jax.fit``) and compares two models
on the same data. A step without an observed entry contributes 0; a partly missing observation,
its observed entries alone. What each estimate is:

* ``gaussian_log_evidence``: the density of ``y`` under a Gaussian predictive ``N(mean, S)``:
  exact for the Kalman filter (the true predictive), the innovation density of the ensemble
  Kalman filters (the forecast ensemble's predicted observations, their sample covariance plus
  ``R``; for non-Gaussian noise or a ``Likelihood``, their Gaussian stand-in).
* ``log_mean_weight``: the particle filter's ``log (1/N) sum_i p(y | x_i)`` over the propagated
  particles: its exponential is an unbiased estimate of ``p(y_k | y_1 .. y_{k-1})`` given the
  previous step's particles, and the product over steps an unbiased estimate of the record's
  likelihood (the log of it is biased low, by about half its variance).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp

from csf_jax import _linalg
from csf_jax.ssm import _masked_cov, observed


def gaussian_log_density(residual: jax.Array, chol: jax.Array, mask: jax.Array) -> jax.Array:
    """``log N(r; 0, S)`` over the observed entries: ``residual (m,)`` with 0 on the missing
    ones, ``chol (m, m)`` the lower Cholesky factor of ``S`` masked to the identity on missing rows
    and columns (so the missing block adds nothing to the quadratic form or the determinant),
    ``mask (m,)`` bool the observed entries."""
    white = _linalg.solve_lower(chol, residual)
    log_det = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))
    n_obs = jnp.sum(mask).astype(residual.dtype)
    return -0.5 * (jnp.sum(white * white) + log_det + n_obs * math.log(2.0 * math.pi))


@_linalg.precise
def gaussian_log_evidence(predicted: jax.Array, R: jax.Array, y: jax.Array) -> jax.Array:
    """The innovation density of an ensemble Kalman update: ``log N(y; mean_i p_i, C + R)`` over
    the observed entries of ``y (m,)``, with ``predicted (N, m)`` the members' predicted
    observations, ``C`` their sample covariance (N - 1 denominator) and ``R (m, m)`` the noise
    covariance (its Gaussian stand-in). A scalar; 0 when no entry is observed."""
    n = predicted.shape[0]
    mask = observed(y)
    centre = predicted.mean(axis=0)
    anomalies = jnp.where(mask, predicted - centre, 0.0)
    cov = anomalies.T @ anomalies / (n - 1) + R
    chol = _linalg.cholesky(_masked_cov(cov, mask))
    return gaussian_log_density(jnp.where(mask, jnp.where(mask, y, 0.0) - centre, 0.0), chol, mask)


def log_mean_weight(log_weights: jax.Array) -> jax.Array:
    """``log (1/N) sum_i exp(log_weights_i)`` of unnormalised ``log_weights (N,)``: the particle
    filter's one-step evidence when they are the normalised likelihoods of its propagated
    particles."""
    return logsumexp(log_weights) - jnp.log(log_weights.shape[0]).astype(log_weights.dtype)
