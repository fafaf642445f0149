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

from csf_jax import _checks
from csf_jax.filters.driver import Method, StepOutput, run
from csf_jax.filters.result import FilterResult
from csf_jax.problems.linear import LinearGaussian, linear_source, to_model
from csf_jax.ssm import StateSpaceModel


def kalman_filter(obs, *, lg: LinearGaussian | StateSpaceModel, progress=None) -> FilterResult:
    """Filtered means and stds of ``x_1 .. x_K`` given ``obs (K, m) = y_1 .. y_K`` (NaN: missing).

    lg: the ``LinearGaussian`` (``csf_jax.problems.linear.linear_gaussian``), or the
      ``StateSpaceModel`` that ``to_model`` made of one (what the ensemble filters take).
    Returns ``FilterResult(mean (K, d), std (K, d), finite (K,))`` with
    ``std = sqrt(diag(P_{k|k}))``; no ensembles, no ESS. Use ``kalman_filter_cov`` for the full
    covariances.
    """
    result = _run(obs, lg, progress)
    return result._replace(info=None)


def kalman_filter_cov(obs, lg: LinearGaussian | StateSpaceModel):
    """Filtered means ``(K, d)`` and covariances ``(K, d, d)`` of ``x_1 .. x_K``."""
    result = _run(obs, lg, None, check_finite=False)
    return result.mean, result.info["cov"]


def as_linear_gaussian(lg, name: str = "kalman_filter") -> LinearGaussian:
    """``lg`` itself if a ``LinearGaussian``; for a ``StateSpaceModel`` made by ``to_model``, the
    ``LinearGaussian`` it came from; else a TypeError saying what is expected."""
    if isinstance(lg, LinearGaussian):
        return lg
    if isinstance(lg, StateSpaceModel):
        source = linear_source(lg)
        if source is None:
            raise TypeError(f"{name}: lg={lg.name!r} is a StateSpaceModel not made by "
                            f"to_model(linear_gaussian(...)), so it has no matrices to read; pass "
                            f"the LinearGaussian (csf_jax.problems.linear.linear_gaussian) or "
                            f"to_model of one")
        return source
    raise TypeError(f"{name}: lg must be a LinearGaussian (csf_jax.problems.linear."
                    f"linear_gaussian) or to_model of one, got {type(lg).__name__}")


def _run(obs, lg, progress, check_finite: bool = False) -> FilterResult:
    lg = as_linear_gaussian(lg)
    obs = jnp.asarray(obs)
    dtype = _checks.compute_dtype(obs.dtype) if jnp.issubdtype(obs.dtype, jnp.floating) \
        else jnp.float32
    params = tuple(jnp.asarray(a, dtype) for a in (lg.A, lg.H, lg.process_cov(), lg.obs_cov()))
    state0 = (jnp.asarray(lg.m0, dtype), jnp.asarray(lg.p0_std, dtype) ** 2
              * jnp.eye(lg.dim, dtype=dtype))
    return run(KALMAN, obs, state0, model=to_model(lg), key=jax.random.key(0), params=params,
               check_finite=check_finite, progress=progress)


def _init(model, config, params, state0, key):
    return state0, key


def _step(model, config, params, state, y, key, time):
    """Predict with ``A, Q`` and update on ``y (m,)`` with ``H, R``; state ``(mean (d,), cov)``."""
    A, H, Q, R = params
    mean, cov = state
    d, m = A.shape[0], H.shape[0]
    eye_d, eye_m = jnp.eye(d, dtype=A.dtype), jnp.eye(m, dtype=A.dtype)
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
    std = jnp.sqrt(jnp.clip(jnp.diagonal(cov), 0.0))
    return (mean, cov), StepOutput(mean, std, None, {"cov": cov})


KALMAN = Method("kalman_filter", _init, _step, ensemble=False, label="Kalman")
