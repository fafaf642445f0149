"""The stochastic ensemble Kalman filter with perturbed observations.

Each step propagates the ensemble, optionally inflates its anomalies, and moves every member by
the sample Kalman gain ``K = C_xy (C_yy + R)^{-1}`` applied to its own perturbed innovation
``y + e_i - h(x_i)``, ``e_i ~ N(0, R)``. ``R`` is the model's observation-noise covariance
(``ObservationNoise.cov``: its ``covariance``, else ``gaussian_std^2 I``, for non-Gaussian noise the
Gaussian stand-in). Exact in the linear-Gaussian limit N -> inf. Missing (NaN) entries of ``y`` are
left out: their innovations and predicted anomalies are zeroed and their rows and columns of ``R``
replaced by the identity's, so the gain acts on the observed entries alone.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from csf_jax._checks import (check_filter_inputs, check_key, check_result_finite, is_concrete,
                             promote)
from csf_jax.filters.result import FilterResult, mark_nonfinite
from csf_jax.ssm import StateSpaceModel, observed, propagate


def ensemble_kalman_filter(obs, ensemble, *, problem: StateSpaceModel, key,
                           return_ensembles: bool = False, inflation=1.0,
                           check_finite: bool = True) -> FilterResult:
    """Run the stochastic EnKF.

    Args:
      obs: (K, m) observations ``y_1 .. y_K``; float, promoted with ``ensemble`` to their common
        float dtype. NaN marks a missing entry (left out of the update); inf is an error.
      ensemble: (N, d) ensemble at time 0.
      problem: the state-space model (static: a hashable NamedTuple).
      key: a JAX PRNG key; the same key gives the same result.
      return_ensembles: also return the analysis ensembles (K, N, d).
      inflation: multiplicative factor on the forecast anomalies (1.0 = none); a positive scalar.
      check_finite: raise FloatingPointError if the mean becomes non-finite (concrete runs only).

    Returns:
      ``FilterResult(mean (K, d), std (K, d), ensembles (K, N, d) | None, ess=None, finite (K,))``,
      mean and std (N-1 denominator) of the analysis ensemble. Under jit/vmap, mean and std are
      NaN and ``finite`` False from a non-finite step on (``mark_nonfinite``).
    """
    check_filter_inputs(obs, ensemble, problem, name="ensemble_kalman_filter")
    check_key(key, name="ensemble_kalman_filter")
    if jnp.ndim(inflation) != 0:
        raise ValueError(f"ensemble_kalman_filter: inflation must be a scalar, got shape "
                         f"{jnp.shape(inflation)}")
    if is_concrete(inflation) and not (np.isfinite(inflation) and float(inflation) > 0):
        raise ValueError(f"ensemble_kalman_filter: inflation must be positive and finite, got "
                         f"{inflation}")
    obs, ensemble = promote(obs, ensemble)
    result = mark_nonfinite(_ensemble_kalman_filter(obs, ensemble, key, inflation, problem=problem,
                                                    return_ensembles=bool(return_ensembles)), obs)
    if check_finite:
        check_result_finite("ensemble_kalman_filter", result)
    return result


def enkf_analysis(key, forecast, y, model: StateSpaceModel):
    """Perturbed-observation update of ``forecast (N, d)`` on ``y (m,)``; returns ``(N, d)``.

    Sample covariances use N-1 denominators; the gain is applied through a Cholesky solve of
    ``C_yy + R`` (never an explicit inverse). NaN entries of ``y`` are missing (module docstring).
    """
    n, m = forecast.shape[0], y.shape[0]
    mask = observed(y)
    both = mask[:, None] & mask[None, :]
    predicted = jax.vmap(model.observe)(forecast).astype(forecast.dtype)
    x_anom = forecast - forecast.mean(axis=0)
    y_anom = jnp.where(mask, predicted - predicted.mean(axis=0), 0.0)
    c_xy = x_anom.T @ y_anom / (n - 1)
    c_yy = y_anom.T @ y_anom / (n - 1)
    R = model.obs_noise.cov(m, forecast.dtype)
    S = c_yy + jnp.where(both, R, jnp.eye(m, dtype=forecast.dtype))
    e = model.obs_noise.gaussian_draws(key, predicted.shape, forecast.dtype)
    innovations = jnp.where(mask, jnp.where(mask, y, 0.0) + e - predicted, 0.0)
    weights = jsl.cho_solve(jsl.cho_factor(S, lower=True), innovations.T)
    return forecast + (c_xy @ weights).T


def _enkf_step(model: StateSpaceModel, return_ensembles: bool, inflation, ensemble, key, y):
    """Forecast, inflate and analyse one step on ``ensemble (N, d)`` with ``y (m,)``."""
    k_prop, k_obs = jax.random.split(key)
    forecast = propagate(model, k_prop, ensemble).astype(ensemble.dtype)
    center = forecast.mean(axis=0)
    forecast = center + inflation * (forecast - center)
    analysis = enkf_analysis(k_obs, forecast, y, model)
    mean = analysis.mean(axis=0)
    std = analysis.std(axis=0, ddof=1)
    return analysis, (mean, std, analysis if return_ensembles else None)


@functools.partial(jax.jit, static_argnames=("problem", "return_ensembles"))
def _ensemble_kalman_filter(obs, ensemble, key, inflation, *, problem: StateSpaceModel,
                            return_ensembles: bool) -> FilterResult:
    """The jitted scan over time; inputs already checked and promoted to one float dtype.
    ``obs (K, m)``, ``ensemble (N, d)``."""
    keys = jax.random.split(key, obs.shape[0])
    inflation = jnp.asarray(inflation, ensemble.dtype)

    def step(ens, inputs):
        k, y = inputs
        return _enkf_step(problem, return_ensembles, inflation, ens, k, y)

    _, (mean, std, ensembles) = jax.lax.scan(step, ensemble, (keys, obs))
    return FilterResult(mean=mean, std=std, ensembles=ensembles)
