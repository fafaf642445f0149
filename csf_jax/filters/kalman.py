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

from csf_jax import _checks, _linalg
from csf_jax.evidence import gaussian_log_density
from csf_jax.filters.driver import Kernel, Method, StepOutput, refuse_settings, run_kernel
from csf_jax.filters.result import FilterResult
from csf_jax.parametric import ParametricModel
from csf_jax.problems.linear import LinearGaussian, linear_gaussian, linear_source, to_model
from csf_jax.ssm import StateSpaceModel


@_checks.renamed_keywords(lg="model")
def kalman_filter(obs, *, model: LinearGaussian | StateSpaceModel, progress=None) -> FilterResult:
    """Filtered means and stds of ``x_1 .. x_K`` given ``obs (K, m) = y_1 .. y_K`` (NaN: missing).

    Args:
      obs: (K, m) observations ``y_1 .. y_K``; NaN marks a missing entry.
      model: the ``LinearGaussian`` (``csf_jax.problems.linear.linear_gaussian``), the
        ``StateSpaceModel`` that ``to_model`` made of one (what the ensemble filters take), or a
        ``csf_jax.ParametricModel`` whose ``build(theta)`` returns a ``LinearGaussian``: its
        numbers traced (``jax.grad`` of ``log_evidence`` is exact; one compilation for every
        theta of the same sizes). Its matrices are not validated: the caller owns them.
      progress: optional host callback ``k -> None`` at every filter step.

    Returns:
      ``FilterResult``: mean (K, d), std (K, d) with ``std = sqrt(diag(P_{k|k}))``, finite (K,),
        ``log_evidence`` (K,) the exact ``log p(y_k | y_1 .. y_{k-1})`` (the innovation's
        Gaussian density over the observed entries); no ensembles, no ESS. Use
        ``kalman_filter_cov`` for the full covariances.
    """
    result = _run(obs, model, progress)
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
            raise TypeError(f"{name}: model={lg.name!r} is a StateSpaceModel not made by "
                            f"to_model(linear_gaussian(...)), so it has no matrices to read; pass "
                            f"the LinearGaussian (csf_jax.problems.linear.linear_gaussian) or "
                            f"to_model of one")
        return source
    raise TypeError(f"{name}: model must be a LinearGaussian (csf_jax.problems.linear."
                    f"linear_gaussian) or to_model of one, got {type(lg).__name__}")


def _run(obs, lg, progress, check_finite: bool = False) -> FilterResult:
    parametric = isinstance(lg, ParametricModel)
    lg = _built_linear_gaussian(lg) if parametric else as_linear_gaussian(lg)
    obs = jnp.asarray(obs)
    dtype = _checks.compute_dtype(obs.dtype) if jnp.issubdtype(obs.dtype, jnp.floating) \
        else jnp.float32
    params = tuple(jnp.asarray(a, dtype) for a in (lg.A, lg.H, lg.process_cov(), lg.obs_cov()))
    state0 = (jnp.asarray(lg.m0, dtype), jnp.asarray(lg.p0_std, dtype) ** 2
              * jnp.eye(lg.dim, dtype=dtype))
    # a ParametricModel's numbers reach the scan as its traced params alone: the static model is
    # a stand-in of its sizes (the step reads nothing else), so every theta shares one compilation
    model = _sizes_model(lg.dim, lg.obs_dim, lg.name) if parametric else to_model(lg)
    return run_kernel(KALMAN, obs, state0, model=model, key=jax.random.key(0),
                      params=params, check_finite=check_finite, progress=progress)


def _built_linear_gaussian(pm: ParametricModel) -> LinearGaussian:
    """``pm.build(pm.theta)``, which must be a ``LinearGaussian`` (made directly, its numbers
    possibly traced); TypeError otherwise."""
    lg = pm.build(pm.theta)
    if not isinstance(lg, LinearGaussian):
        raise TypeError(f"kalman_filter: a ParametricModel's build(theta) must return a "
                        f"LinearGaussian (csf_jax.problems.linear.LinearGaussian(A, H, q_std, "
                        f"r_std, m0, p0_std, num_steps, name)), got {type(lg).__name__}")
    return lg


def _sizes_model(dim: int, obs_dim: int, name: str) -> StateSpaceModel:
    """A linear-Gaussian model of these sizes (cached: one object per sizes), the Kalman scan's
    static model when the numbers come from a ``ParametricModel``."""
    return to_model(linear_gaussian(dim, obs_dim, name=name))


def method(*settings, **named) -> Method:
    """The exact Kalman filter as a ``Method``: ``csf_jax.run(method(), obs, None, model=lg,
    key=key)`` with ``lg`` a ``LinearGaussian`` or ``to_model`` of one (the ensemble and the key
    are not used: it starts from the model's own initial law). It has no settings: any argument
    (a config object, say) is a TypeError."""
    refuse_settings("kalman_filter", settings, named)
    return Method(KALMAN._replace(runner=_run_method))


def _run_method(method, obs, ensemble, *, model, key, inputs=None, return_ensembles=False,
                check_finite=True, progress=None) -> FilterResult:
    if inputs is not None or return_ensembles:
        raise ValueError("kalman_filter: takes no inputs and has no ensembles to return")
    return _run(obs, model, progress, check_finite)._replace(info=None)


def _init(model, config, params, state0, key):
    return state0, key


@_linalg.precise
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
    factor = jsl.cho_factor(S, lower=True)
    gain = jsl.cho_solve(factor, H_k @ cov).T
    innovation = jnp.where(mask, y - H @ mean, 0.0)
    log_evidence = gaussian_log_density(innovation, jnp.tril(factor[0]), mask)
    mean = mean + gain @ innovation
    J = eye_d - gain @ H_k
    cov = J @ cov @ J.T + gain @ R_k @ gain.T
    cov = 0.5 * (cov + cov.T)
    std = jnp.sqrt(jnp.clip(jnp.diagonal(cov), 0.0))
    return (mean, cov), StepOutput(mean, std, None, {"cov": cov}, log_evidence)


KALMAN = Kernel("kalman_filter", _init, _step, ensemble=False, label="Kalman")
