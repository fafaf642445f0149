"""The stochastic ensemble Kalman filter with perturbed observations.

Each step propagates the ensemble, optionally inflates its anomalies, and moves every member by
the sample Kalman gain ``K = C_xy (C_yy + R)^{-1}`` applied to its own perturbed innovation
``y + e_i - h(x_i)``, ``e_i ~ N(0, R)``. ``R`` is the model's observation-noise covariance
(``ObservationNoise.cov``: its ``covariance``, else ``gaussian_std^2 I``, for non-Gaussian noise the
Gaussian stand-in; for a non-additive ``Likelihood``, ``E[y | x_i]`` stands for ``h(x_i)`` and the
ensemble-mean ``Var[y | x_i]`` for R: ``ssm.gaussian_standin``). Exact in the linear-Gaussian limit N -> inf. Missing (NaN) entries of ``y`` are
left out: their innovations and predicted anomalies are zeroed and their rows and columns of ``R``
replaced by the identity's, so the gain acts on the observed entries alone.
"""

from __future__ import annotations

import numbers

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from csf_jax import _linalg, _random
from csf_jax._checks import is_concrete, renamed_keywords
from csf_jax.evidence import gaussian_log_evidence
from csf_jax.filters.driver import Kernel, Method, StepOutput, run
from csf_jax.filters.result import FilterResult
from csf_jax.ssm import StateSpaceModel, gaussian_standin, is_additive, observed, propagate


@renamed_keywords(problem="model")
def ensemble_kalman_filter(obs, ensemble, *, model: StateSpaceModel, key, inputs=None,
                           return_ensembles: bool = False, inflation=1.0,
                           check_finite: bool = True, progress=None) -> FilterResult:
    """Run the stochastic EnKF.

    Args:
      obs: (K, m) observations ``y_1 .. y_K``; float, promoted with ``ensemble`` to their common
        float dtype. NaN marks a missing entry (left out of the update); inf is an error.
      ensemble: (N, d) ensemble at time 0.
      model: the state-space model (static: a hashable NamedTuple). A non-additive
        ``Likelihood`` needs its Gaussian stand-in (``mean`` and ``variance``).
      key: a JAX PRNG key; the same key gives the same result.
      inputs: a time-varying model's per-step inputs (leading axis K), or None.
      return_ensembles: also return the analysis ensembles (K, N, d).
      inflation: multiplicative factor on the forecast anomalies (1.0 = none); a positive scalar.
      check_finite: raise FloatingPointError if the mean becomes non-finite (concrete runs only).
      progress: optional host callback ``k -> None`` at every step (and a line on stderr around
        the first compilation).

    Returns:
      ``FilterResult(mean (K, d), std (K, d), ensembles (K, N, d) | None, ess=None, finite (K,),
      log_evidence (K,))``, mean and std (N-1 denominator) of the analysis ensemble;
      ``log_evidence`` the innovation density ``log N(y_k; mean, C + R)`` of the inflated forecast
      ensemble's predicted observations (``csf_jax.evidence``: exact as N grows for a
      linear-Gaussian model, with the Gaussian stand-in of any other noise or likelihood). Under jit/vmap, mean and std are
      NaN and ``finite`` False from a non-finite step on (``mark_nonfinite``).
    """
    return run(method(inflation), obs, ensemble, model=model, key=key, inputs=inputs,
               return_ensembles=return_ensembles, check_finite=check_finite, progress=progress)


def method(inflation=1.0) -> Method:
    """The stochastic EnKF as a ``Method`` for ``csf_jax.run``.

    Args:
      inflation: multiplicative factor on the forecast anomalies (1.0 = none); a positive scalar
        (a Python number or a 0-d array), traced (a sweep over it compiles once). Anything else
        (a config object, a bool) is a TypeError.
    """
    if not _is_real(inflation):
        raise TypeError(f"ensemble_kalman_filter: inflation must be a positive number (a float or "
                        f"a scalar array), got {type(inflation).__name__}; the EnKF takes no "
                        f"config object")
    if jnp.ndim(inflation) != 0:
        raise ValueError(f"ensemble_kalman_filter: inflation must be a scalar, got shape "
                         f"{jnp.shape(inflation)}")
    if is_concrete(inflation) and not (np.isfinite(inflation) and float(inflation) > 0):
        raise ValueError(f"ensemble_kalman_filter: inflation must be positive and finite, got "
                         f"{inflation}")
    return Method(ENSEMBLE_KALMAN_FILTER, None, jnp.asarray(inflation))


def _is_real(value) -> bool:
    """A real number: a Python int or float, or an array (or tracer) of an int or float dtype;
    not a bool."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, numbers.Real):
        return True
    dtype = getattr(value, "dtype", None)
    return dtype is not None and (jnp.issubdtype(dtype, jnp.floating)
                                  or jnp.issubdtype(dtype, jnp.integer))


@_linalg.precise
def enkf_analysis(key, forecast, y, model: StateSpaceModel):
    """Perturbed-observation update of ``forecast (N, d)`` on ``y (m,)``; returns ``(N, d)``.

    Sample covariances use N-1 denominators; the gain is applied through a Cholesky solve of
    ``C_yy + R`` (never an explicit inverse). NaN entries of ``y`` are missing (module docstring).
    """
    n, m = forecast.shape[0], y.shape[0]
    mask = observed(y)
    both = mask[:, None] & mask[None, :]
    predicted, R = gaussian_standin(model, forecast)
    x_anom = forecast - forecast.mean(axis=0)
    y_anom = jnp.where(mask, predicted - predicted.mean(axis=0), 0.0)
    c_xy = x_anom.T @ y_anom / (n - 1)
    c_yy = y_anom.T @ y_anom / (n - 1)
    S = c_yy + jnp.where(both, R, jnp.eye(m, dtype=forecast.dtype))
    e = _gaussian_draws(model, R, key, predicted.shape, forecast.dtype)
    innovations = jnp.where(mask, jnp.where(mask, y, 0.0) + e - predicted, 0.0)
    weights = jsl.cho_solve(jsl.cho_factor(S, lower=True), innovations.T)
    return forecast + (c_xy @ weights).T


def _gaussian_draws(model: StateSpaceModel, R, key, shape, dtype):
    """Observation perturbations ``(N, m)`` of ``N(0, R)``: the noise's own Gaussian draws where
    it is additive, else from the stand-in's diagonal ``R``."""
    if is_additive(model):
        return model.obs_noise.gaussian_draws(key, shape, dtype)
    return _random.normal(key, shape, dtype) * jnp.sqrt(jnp.diagonal(R))


def _init(model, config, inflation, ensemble, key):
    return ensemble, key


def _step(model: StateSpaceModel, config, inflation, ensemble, y, key, time):
    """Forecast, inflate and analyse one step on ``ensemble (N, d)`` with ``y (m,)``."""
    k_prop, k_obs = jax.random.split(key)
    forecast = propagate(model, k_prop, ensemble).astype(ensemble.dtype)
    center = forecast.mean(axis=0)
    forecast = center + inflation.astype(ensemble.dtype) * (forecast - center)
    analysis = enkf_analysis(k_obs, forecast, y, model)
    return analysis, StepOutput(analysis.mean(axis=0), analysis.std(axis=0, ddof=1), analysis,
                                log_evidence=gaussian_log_evidence(
                                    *gaussian_standin(model, forecast), y))


def check_standin(name: str):
    """A ``Method.check`` refusing a non-additive likelihood without a Gaussian stand-in."""

    def check(model: StateSpaceModel, config) -> None:
        if not is_additive(model) and (model.obs_noise.mean is None
                                       or model.obs_noise.variance is None):
            raise ValueError(f"{name}: model {model.name!r} has the likelihood "
                             f"{model.obs_noise.name!r} without a Gaussian stand-in "
                             f"(Likelihood.mean and .variance); a Kalman-type filter needs one")

    return check


ENSEMBLE_KALMAN_FILTER = Kernel("ensemble_kalman_filter", _init, _step,
                                check_standin("ensemble_kalman_filter"), label="EnKF")
