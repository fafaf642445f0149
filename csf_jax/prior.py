"""Sources of the prior score ``grad log p_t(x)`` behind one interface.

A ``PriorScore`` is conditioned once per filter step on the propagated ensemble, then evaluated at
every reverse step. Two sources:

* ``learned_prior(network_config)``: CSF proper. The set encoder turns the prior ensemble into a code
  ``c`` (once per filter step), the conditional score net gives ``s(x, t; c)``.
* ``gaussian_prior()``: no training. The Gaussian with the propagated ensemble's mean and covariance,
  diffused in closed form: what an ensemble Kalman filter assumes, and the worst case a prior built
  on it should reach.
* ``exact_mixture_prior()``: no training. Given the previous posterior ensemble ``x_i``, the prior is
  exactly the Gaussian mixture ``(1/N) sum_i N(f(x_i), q^2 I)``; under the VE SDE its marginal at time
  t is ``(1/N) sum_i N(f(x_i), (q^2 + sigma_t^2) I)``, whose score is closed form. It separates the
  sampler's error from the learned prior's.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from csf_jax import _checks, _linalg, networks
from csf_jax.covariance import SAMPLE, CovarianceConfig
from csf_jax.covariance import estimate as estimate_covariance
from csf_jax.mixture import MixtureConfig
from csf_jax.sde import marginal_std


@dataclasses.dataclass(frozen=True)
class PriorConfig:
    """What CSF's prior is built from, besides the trained network (``CSFConfig.prior``).

    Attributes:
      encode_particles: how many particles of the prior ensemble the set encoder of the learned
        prior sees (the first n; particles are exchangeable; ``learned_prior(network, n)``). None:
        all N. The encoder's self-attention costs O(n^2), and the shipped priors were trained on
        sets of 32-128 particles.
      mixture: the mixture prior (``csf_jax.mixture.MixtureConfig``: particle, ensemble and shock
        components weighed by their evidence), or None for the ensemble component alone. It
        needs the ancestral sampler ("kalman" guidance; ``CSFConfig`` refuses it with a DPS
        mode); with ``params=None`` its ensemble component is the ensemble's Gaussian (the
        particle components already are the exact mixture).
      covariance: how the prior ensemble's covariance is estimated wherever the sampler uses the
        ensemble's Gaussian: the Kalman guidance's precision, the Gaussian prior, a Gaussian-base
        learned prior's base and the mixture's ensemble component (``csf_jax.CovarianceConfig``).
        With a DPS mode only a Gaussian-base learned prior built from it reads it; elsewhere an
        estimator other than the sample one is refused, not ignored.
    """

    encode_particles: int | None = 256
    mixture: MixtureConfig | None = MixtureConfig()
    covariance: CovarianceConfig = CovarianceConfig()

    def __post_init__(self):
        _checks.check_fields(self)
        n = self.encode_particles
        if n is not None and n < 2:
            raise ValueError(f"PriorConfig.encode_particles must be None or an int >= 2, got {n!r}")


class PriorScore(NamedTuple):
    """A prior-score source; hashable, so filters take it as a static argument. The constructors
    below are cached: equal arguments give the same object, so jit caches are reused.

    Attributes:
      condition: ``(params, centers (N, d), ensemble (N, d), process_std) -> context`` (a pytree),
        once per filter step. ``centers`` are ``f(x_i)``, ``ensemble`` is ``f(x_i) + v_i``.
      score: ``(params, context, x (N, d), t scalar) -> (N, d)`` the prior score at noise level t.
    """

    name: str
    condition: Callable[..., Any]
    score: Callable[..., jax.Array]


class MixtureContext(NamedTuple):
    """Centers ``(N, d)`` and the per-coordinate variance ``q^2`` of the exact mixture prior."""

    centers: jax.Array
    variance: jax.Array


def mixture_score(x, centers, variance):
    """Score of ``(1/M) sum_j N(centers_j, variance I)`` at ``x (N, d)``; ``centers: (M, d)``.

    Softmax responsibilities over components, computed from squared distances with a matmul.
    """
    sq = (jnp.sum(x * x, -1, keepdims=True) - 2.0 * x @ centers.T
          + jnp.sum(centers * centers, -1)[None, :])
    resp = jax.nn.softmax(-0.5 * sq / variance, axis=-1)
    return (resp @ centers - x) / variance


@functools.cache
def exact_mixture_prior(sigma_max: float = 25.0) -> PriorScore:
    """The exact VE-diffused score of the propagated ensemble as a Gaussian mixture."""

    def condition(params, centers, ensemble, process_std):
        del params, ensemble
        return MixtureContext(centers, jnp.asarray(process_std, centers.dtype) ** 2)

    def score(params, ctx, x, t):
        del params
        return mixture_score(x, ctx.centers, ctx.variance + marginal_std(t, sigma_max) ** 2)

    return PriorScore("exact_mixture", condition, score)


class GaussianContext(NamedTuple):
    """Mean ``(d,)`` and covariance ``(d, d)`` of the propagated ensemble."""

    mean: jax.Array
    cov: jax.Array


@_linalg.precise
def ensemble_moments(ensemble, jitter: float = 1e-6,
                     covariance: CovarianceConfig = SAMPLE) -> GaussianContext:
    """Mean and covariance (``covariance``'s estimator) of ``ensemble (N, d)``, the floor on its
    diagonal (``usable_floor``: the rounding floor where the covariance is singular in its
    dtype)."""
    mean, cov, floor = estimate_covariance(ensemble, covariance, jitter)
    floor = usable_floor(ensemble, cov, floor)
    return GaussianContext(mean, cov + floor * jnp.eye(ensemble.shape[-1], dtype=ensemble.dtype))


@_linalg.precise
def gaussian_score(x, ctx: GaussianContext, sigma):
    """Score of ``N(mean, cov + sigma^2 I)`` at ``x (N, d)``: ``-(cov + sigma^2 I)^{-1} (x - mean)``.

    sigma: a scalar (one factorisation for all rows) or ``(N,)``, one noise level per row.
    """
    sigma = jnp.asarray(sigma, x.dtype)
    eye = jnp.eye(ctx.mean.shape[-1], dtype=x.dtype)
    chol = _linalg.cholesky(ctx.cov + sigma[..., None, None] ** 2 * eye)
    return -_linalg.cho_solve(chol if sigma.ndim else chol[None], x - ctx.mean)


@functools.cache
def gaussian_prior(sigma_max: float = 25.0, covariance: CovarianceConfig = SAMPLE) -> PriorScore:
    """The ensemble's own Gaussian, VE-diffused: score ``-(C + sigma_t^2 I)^{-1} (x - m)``, with
    ``C`` by ``covariance`` (``csf_jax.covariance``: sample, Ledoit-Wolf shrunk or localised)."""

    def condition(params, centers, ensemble, process_std):
        del params, centers, process_std
        return ensemble_moments(ensemble, covariance=covariance)

    def score(params, ctx, x, t):
        del params
        return gaussian_score(x, ctx, marginal_std(t, sigma_max))

    return PriorScore("gaussian", condition, score)


class ResidualContext(NamedTuple):
    """The learned prior's context with a Gaussian base: the code ``(C,)`` and the moments."""

    code: jax.Array
    moments: GaussianContext


def residual_score(params, config: networks.NetworkConfig, ctx: ResidualContext, x, t):
    """Gaussian score of the ensemble plus the net's correction at standardised coordinates.

    ``x: (N, d)``, ``t`` scalar or ``(N,)``; the net sees ``z = (x - m) / s`` with
    ``s = sqrt(diag C + sigma_t^2)`` and its output (a score, ``out / sigma_t``) is rescaled to
    ``out / s``: the correction is measured in units of the diffused ensemble's spread, wherever the
    ensemble sits.
    """
    sigma = jnp.asarray(marginal_std(t, config.sigma_max), x.dtype)[..., None]
    spread = jnp.sqrt(jnp.diagonal(ctx.moments.cov) + sigma ** 2)
    z = (x - ctx.moments.mean) / spread
    correction = networks.score(params, z, t, ctx.code, config) * (sigma / spread)
    return gaussian_score(x, ctx.moments, sigma[..., 0]) + correction


@functools.cache
def learned_prior(config: networks.NetworkConfig = networks.NetworkConfig(),
                  encode_particles: int | None = None,
                  covariance: CovarianceConfig = SAMPLE) -> PriorScore:
    """The conditional score net ``s(x, t; c)`` with ``c`` the set encoder's code of the ensemble.

    Args:
      config: the network's ``NetworkConfig``.
      encode_particles: the encoder sees the first n particles of the ensemble (None: all); with
        ``config.base == "gaussian"`` the moments of the base come from all of them.
      covariance: the estimator of the base's covariance (``CovarianceConfig``).
    """

    def condition(params, centers, ensemble, process_std):
        del centers, process_std
        code = networks.encode(params, ensemble[:encode_particles], config)
        if config.base == "gaussian":
            return ResidualContext(code, ensemble_moments(ensemble, covariance=covariance))
        return code

    def score(params, ctx, x, t):
        if config.base == "gaussian":
            return residual_score(params, config, ctx, x, t)
        return networks.score(params, x, t, ctx, config)

    return PriorScore("learned", condition, score)


@functools.cache
def unconditional_prior(config: networks.NetworkConfig = networks.NetworkConfig()) -> PriorScore:
    """A score net trained on one ensemble alone (no encoder): its code is fixed at zero.

    The from-scratch reference of the prior-quality study, and the per-step model of the score-based
    filter (SF) baseline.
    """

    def condition(params, centers, ensemble, process_std):
        del params, centers, process_std
        return jnp.zeros((config.code_dim,), ensemble.dtype)

    def score(params, code, x, t):
        return networks.score(params, x, t, code, config)

    return PriorScore("unconditional", condition, score)


@_linalg.precise
def gaussian_precision(ensemble, inflation: float = 0.0, jitter: float = 1e-6,
                       covariance: CovarianceConfig = SAMPLE):
    """Precision ``(C + inflation^2 I)^{-1}`` of the ensemble's Gaussian; ``ensemble: (N, d)`` -> (d, d).

    ``C`` is the ``covariance`` estimate (default the sample covariance). It gives the Kalman
    guidance the covariance of ``x_0 | x_t``, ``P_t = (C^{-1} + I / sigma_t^2)^{-1}``, exact for a
    Gaussian prior. ``jitter`` times the mean variance (plus a tiny absolute floor) is added to the
    diagonal, so a collapsed or rank-deficient ensemble (N <= d) still gives a finite precision;
    where ``C`` is singular in the dtype's rounding, the rounding floor instead
    (``usable_floor``). Plain-jnp Cholesky (``csf_jax._linalg``).
    """
    _, cov, floor = estimate_covariance(ensemble, covariance, jitter)
    floor = usable_floor(ensemble, cov, floor)
    eye = jnp.eye(ensemble.shape[-1], dtype=ensemble.dtype)
    chol = _linalg.cholesky(cov + (inflation ** 2 + floor) * eye)
    return _linalg.cho_solve(chol[None], eye)


def usable_floor(ensemble, cov, floor):
    """The diagonal floor for ``cov (d, d)``, the covariance of ``ensemble (N, d)``: ``floor``
    where ``cov + floor I`` is not singular in its dtype, else ``rounding_floor``. Singular: its
    Cholesky factor is not finite, or has a pivot below the rounding floor (the pivots of the
    directions a rank-deficient covariance lacks are about ``floor``). One ``(d, d)``
    factorisation; where the floor stays, the results stay as they were."""
    chol = _linalg.cholesky(cov + floor * jnp.eye(cov.shape[-1], dtype=cov.dtype))
    safe = rounding_floor(ensemble, cov)
    singular = ~jnp.all(jnp.isfinite(chol)) | (jnp.min(jnp.diagonal(chol)) ** 2 < safe)
    return jnp.where(singular, jnp.maximum(floor, safe), floor)


def rounding_floor(ensemble, cov):
    """The least diagonal floor that keeps the precision of ``cov (d, d)``, the covariance of
    ``ensemble (N, d)``, meaningful in its dtype: ``(N + d) eps tr(C)``.

    A rank-deficient sample covariance (N <= d, or an ensemble collapsed onto a few directions)
    has eigenvalues that are 0 in exact arithmetic. Computed, they sit at about ``+- eps ||C||``
    (the Gram product's rounding): with a floor below that (the default 1e-6 of the mean variance,
    against ``eps ||C||`` up to ``d eps`` of it in float32) the factorisation meets a negative
    pivot, or the precision's rounding errors (``eps / floor``) exceed its smallest eigenvalue
    ``1 / ||C||`` and the guidance's ``P^{-1} + I / sigma^2`` comes out indefinite: NaN either
    way. The rounding of the Gram product (``N eps tr(C)``) and of the factorisation (``d eps
    ||A||``) are both below this floor. ``usable_floor`` puts it in only where ``C`` is singular
    in the dtype: elsewhere the floor and the results are as they were. In float64 it is
    negligible."""
    n, d = ensemble.shape
    eps = jnp.finfo(cov.dtype).eps
    return (n + d) * eps * jnp.trace(cov)
