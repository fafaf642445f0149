"""A near-exact reference filter for models that factorise per coordinate, shocks included.

The table's problems almost factorise: the observation ``y_i = h(x_i) + w_i`` sees one coordinate
through i.i.d. noise, the process noise is i.i.d., and the drift couples coordinates weakly or not
at all (``A_n``: 0.1 dt = 0.001 per step on the super-diagonal). So the filtering density is close to
the product of its one-dimensional marginals, and each marginal is one-dimensional: a particle
filter with tens of thousands of particles per coordinate is near-exact there, where a joint
particle filter in 10-20 dimensions collapses.

The reference keeps ``M`` particles per coordinate, ``particles: (M, d)``, column ``j`` being the
particle system of coordinate ``j``; columns are resampled independently, so a row is a draw from
the product of the marginals, and ``drift`` applied to rows propagates each coordinate with its
neighbours drawn from their marginals (the product-of-marginals closure of a coupled drift).

Shocks. The truth is shocked at unknown steps (``model.shock``, e.g. every coordinate jumps by
``+-1``, or the state is reflected); the CSF, EnKF and PF of the table do not model them, the
reference does. Each step weighs two hypotheses, no shock and shock, with the prior probability
``P(step k is a shock step)`` estimated from ``model.shock_times`` by Monte Carlo: their likelihoods
are products over coordinates of the per-coordinate predictive likelihoods, so all coordinates vote
on whether a shock happened. The posterior marginal of each coordinate is the hypotheses' mixture.
Two approximations, both small here: the marginals are collapsed to a product every step, and the
shock prior is the per-step marginal (it ignores that a run has exactly ``shock_count`` shocks).
How close it is, is measured, not assumed: rerun with more particles, its RMSE barely moves
(measured on docs/design.md, the reference filter's row), and ``tests/test_reference.py`` checks
it against the Kalman filter on a linear-Gaussian model.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp

from csf_jax import _checks, _random
from csf_jax.filters.driver import Kernel, Method, StepOutput, run, run_kernel
from csf_jax.filters.result import FilterResult
from csf_jax.ssm import (
    StateSpaceModel,
    check_model,
    entry_log_likelihood,
    is_additive,
    is_isotropic,
)


class ReferenceConfig(NamedTuple):
    """Settings of the reference filter; defaults made the table's reference row.

    Attributes:
      particles: M particles per coordinate.
      model_shocks: weigh the shock hypothesis each step (False: a plain per-coordinate PF).
      shock_draws: Monte Carlo draws of ``model.shock_times`` for the per-step shock probability.
    """

    particles: int = 20000
    model_shocks: bool = True
    shock_draws: int = 4096



def shock_probability(model: StateSpaceModel, num_steps: int, draws: int = 4096,
                      seed: int = 0) -> np.ndarray:
    """``(K,)``: the probability that the truth is shocked at step k (``x_{k+1}``), estimated from
    ``draws`` draws of ``model.shock_times``, floored at ``0.5 / draws`` inside the steps it ever hits."""
    with jax.ensure_compile_time_eval():  # host values even when called under jit/vmap
        keys = jax.random.split(jax.random.key(seed), draws)
        hits = np.asarray(jax.vmap(lambda k: model.shock_times(k, num_steps))(keys))
    p = hits.mean(0)
    return np.where(p > 0, np.maximum(p, 0.5 / draws), 0.0)


def check_separable(model: StateSpaceModel, name: str = "reference_filter") -> None:
    """Refuse a model whose observation does not see each coordinate on its own (``y_i = h(x_i) + w_i``)."""
    if model.time_varying:
        raise ValueError(f"{name}: needs a time-invariant model")
    if not is_isotropic(model) or (is_additive(model) and model.obs_noise.covariance is not None):
        raise ValueError(f"{name}: needs i.i.d. process and observation noise (the model has a "
                         f"structured process_noise or a noise covariance)")
    if model.obs_dim != model.dim:
        raise ValueError(f"{name}: needs obs_dim == dim (one observation per coordinate), got "
                         f"{model.obs_dim} and {model.dim}")
    with jax.ensure_compile_time_eval():
        jac = np.asarray(jax.jacfwd(model.observe)(jnp.linspace(-1.3, 1.7, model.dim)))
    if np.any(np.abs(jac - np.diag(np.diag(jac))) > 1e-6 * (1 + np.abs(jac).max())):
        raise ValueError(f"{name}: the observation mixes coordinates (its Jacobian is not "
                         f"diagonal); the reference filter needs y_i = h(x_i) + w_i")


def _coordinate_loglik(model: StateSpaceModel, y, particles):
    """``(M, d)`` log p(y_j | x_j) of every particle of every coordinate (entries independent);
    0 where ``y_j`` is missing (NaN)."""
    return jax.vmap(lambda x: entry_log_likelihood(model, y, x))(particles)


def _resample_columns(key, candidates, log_w, m: int):
    """``m`` systematic draws per column from ``candidates (C, d)`` with ``log_w (C, d)``."""
    w = jnp.exp(log_w - logsumexp(log_w, axis=0))
    cdf = jnp.cumsum(w, axis=0)
    cdf = cdf / cdf[-1]
    u = (jnp.arange(m, dtype=cdf.dtype)[:, None]
         + jax.random.uniform(key, (1, candidates.shape[1]), cdf.dtype)) / m
    idx = jax.vmap(lambda c, v: jnp.searchsorted(c, v, side="left"), in_axes=1, out_axes=1)(cdf, u)
    idx = jnp.clip(idx, 0, candidates.shape[0] - 1)
    return jnp.take_along_axis(candidates, idx, axis=0)


def _init(model, config: ReferenceConfig, shock_prob, particles, key):
    return particles, key


def _step(model: StateSpaceModel, config: ReferenceConfig, shock_prob, parts, y, key, time):
    """One step of the per-coordinate filters ``particles (M, d)``; ``shock_prob (K,)``."""
    m = parts.shape[0]
    k_prop, k_shock, k_roll, k_res = jax.random.split(key, 4)
    # systematic resampling leaves every column sorted by ancestor: roll each column by its own
    # random offset, so that a row pairs unrelated particles before a coupled drift sees it
    offset = jax.random.randint(k_roll, (1, model.dim), 0, m)
    parts = jnp.take_along_axis(parts, (jnp.arange(m)[:, None] + offset) % m, axis=0)
    prior = (jax.vmap(model.drift)(parts)
             + model.process_std * _random.normal(k_prop, parts.shape, parts.dtype))
    ll0 = _coordinate_loglik(model, y, prior)
    if not config.model_shocks:
        post = _resample_columns(k_res, prior, ll0, m)
        return post, StepOutput(*_moments(prior, ll0))
    p_shock = shock_prob[time.k - 1].astype(parts.dtype)
    shocked = jax.vmap(model.shock)(jax.random.split(k_shock, m), prior)
    ll1 = _coordinate_loglik(model, y, shocked)
    # log predictive likelihood of each hypothesis: product over coordinates
    ev0 = jnp.sum(logsumexp(ll0, axis=0) - jnp.log(m))
    ev1 = jnp.sum(logsumexp(ll1, axis=0) - jnp.log(m))
    lp0 = jnp.log1p(-p_shock) + ev0
    lp1 = jnp.where(p_shock > 0, jnp.log(jnp.maximum(p_shock, 1e-30)) + ev1, -jnp.inf)
    share = jnp.exp(lp1 - jnp.logaddexp(lp0, lp1))  # posterior probability of a shock
    candidates = jnp.concatenate([prior, shocked], axis=0)
    log_w = _candidate_weights(share, ll0, ll1)
    post = _resample_columns(k_res, candidates, log_w, m)
    return post, StepOutput(*_moments(candidates, log_w))


def _check(model: StateSpaceModel, config: ReferenceConfig) -> None:
    check_separable(model)
    if int(config.particles) < 2 or int(config.shock_draws) < 1:
        raise ValueError(f"reference_filter: needs particles >= 2 and shock_draws >= 1, got "
                         f"{config.particles} and {config.shock_draws}")


REFERENCE = Kernel("reference_filter", _init, _step, _check, label="reference",
                   discrete=True)


def _candidate_weights(share, ll0, ll1):
    """``(2M, d)`` log weights of the no-shock and shock candidates: the hypothesis' probability
    (``1 - share``, ``share``) times the within-hypothesis normalised likelihood weight."""
    w0 = jnp.log1p(-share) + ll0 - logsumexp(ll0, axis=0)
    w1 = jnp.log(jnp.maximum(share, 1e-37)) + jnp.where(share > 0, ll1 - logsumexp(ll1, axis=0),
                                                         -jnp.inf)
    return jnp.concatenate([w0, w1], axis=0)


def _moments(candidates, log_w):
    w = jnp.exp(log_w - logsumexp(log_w, axis=0))
    mean = jnp.sum(w * candidates, axis=0)
    return mean, jnp.sqrt(jnp.sum(w * (candidates - mean) ** 2, axis=0))


@_checks.renamed_keywords(problem="model")
def reference_filter(obs, ensemble, *, model: StateSpaceModel, key,
                     config: ReferenceConfig = ReferenceConfig(),
                     check_finite: bool = True) -> FilterResult:
    """Run the per-coordinate reference filter.

    Args:
      obs: (K, m) observations ``y_1 .. y_K``, m == d, ``y_i`` seeing only ``x_i``; NaN: missing.
      ensemble: (N, d) initial particles; the filter starts from ``config.particles`` of them per
        coordinate, drawn with replacement column by column (N = config.particles: used as is).
      model: the state-space model (static).  key: a ``jax.random.key``.
      config: ``ReferenceConfig``.
    Returns:
      ``FilterResult(mean (K, d), std (K, d))``: the weighted moments of the mixture over the
      shock hypotheses, before resampling.
    """
    return run(method(config), obs, ensemble, model=model, key=key, check_finite=check_finite)


def method(config: ReferenceConfig = ReferenceConfig(), own_start: bool = False) -> Method:
    """The reference filter as a ``Method`` for ``csf_jax.run``.

    Args:
      config: ``ReferenceConfig``.
      own_start: start from ``config.particles`` draws of the model's
        initial law (key ``fold_in(key, 1)``) instead of the ensemble given to ``run``: the tables'
        reference, near-exact whatever N the other filters get.
    """
    if not isinstance(config, ReferenceConfig):
        raise TypeError(f"reference_filter: config must be a ReferenceConfig, got "
                        f"{type(config).__name__}")
    return Method(REFERENCE._replace(runner=_run_method), (config, bool(own_start)))


def _run_method(method, obs, ensemble, *, model, key, inputs=None, return_ensembles=False,
                check_finite=True, progress=None) -> FilterResult:
    config, own_start = method.config
    if inputs is not None or return_ensembles:
        raise ValueError("reference_filter: takes no inputs and returns no ensembles")
    if own_start:
        check_model(model, "reference_filter")
        ensemble = model.initial_ensemble(jax.random.fold_in(key, 1), config.particles).astype(
            jnp.result_type(ensemble))
    _checks.check_filter_inputs(obs, ensemble, model, name="reference_filter")
    _checks.check_key(key, name="reference_filter")
    _check(model, config)
    k_init, k_run = jax.random.split(key)
    m = int(config.particles)
    ensemble = jnp.asarray(ensemble)
    if ensemble.shape[0] != m:
        idx = jax.random.randint(k_init, (m, model.dim), 0, ensemble.shape[0])
        ensemble = jnp.take_along_axis(ensemble, idx, axis=0)
    K = jnp.shape(obs)[0]
    p = (shock_probability(model, K, config.shock_draws) if config.model_shocks
         else np.zeros(K))
    return run_kernel(REFERENCE, obs, ensemble, model=model, key=k_run, config=config,
                      params=jnp.asarray(p, jnp.result_type(jnp.asarray(obs).dtype,
                                                            ensemble.dtype)),
                      check_finite=check_finite, progress=progress)
