"""The result type shared by every filter."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class FilterResult(NamedTuple):
    """What a filter returns; a pytree, so ``jax.vmap`` over runs batches every field.

    Attributes:
      mean: (K, d) filtered mean of ``x_k`` given ``y_1 .. y_k``, for k = 1 .. K.
      std: (K, d) per-coordinate spread (ensemble or posterior std).
      ensembles: (K, N, d) posterior ensembles, or None unless ``return_ensembles=True``
        (the Kalman filter has no ensemble and always returns None).
      ess: (K,) effective sample size ``1 / sum(w^2)`` before resampling (particle filter only),
        else None. A concrete run whose ESS falls below ``driver.COLLAPSED_ESS`` (1.5: one
        particle holds the weight) warns once (RuntimeWarning), naming the first such step.
      finite: (K,) bool, False from the first step whose observation is infinite or whose mean or
        std is non-finite on; mean and std are NaN there (``mark_nonfinite``). NaN observations
        are missing, not bad. A filter whose state lost its numbers at a step reports that step's
        mean as NaN even where its resampling would hide it (CSF: a non-finite forecast member or
        prior covariance), so a diverged run never comes back as finite numbers from an ensemble
        that recovered by dropping the overflowed members. Concrete calls refuse infinite
        observations and raise on a non-finite mean (``check_finite=True``), so this matters
        under ``jax.jit``/``jax.vmap``. None only for results built by hand.
      info: dict of per-step diagnostics, each stacked over the K steps from the filter step's
        ``StepOutput.info``, or None where the filter reports none. Exactly:

        * CSF with the mixture prior (``PriorConfig.mixture``, the default):
          ``particle_weight`` and ``shock_weight``, each ``(K,)``, the posterior weights of the
          mixture's particle and shock components (the ensemble component has the rest), and
          ``dropped`` ``(K,)`` int32, the members whose forecast went wild and were replaced
          (``MixtureConfig.wild_ranges``; a concrete call warns where it is not 0). CSF
          without the mixture (``csf_jax.PAPER``): None; it has no bandwidth or other per-step
          setting to report.
        * The Kalman filter's step reports ``cov`` ``(K, d, d)``, the filtered covariances;
          ``kalman_filter`` and ``csf_jax.run(csf_jax.methods.kalman(), ...)`` drop it (None),
          ``csf_jax.filters.kalman.kalman_filter_cov`` returns it.
        * The particle filter's step reports ``ess``, which goes to ``FilterResult.ess``
          (info None).
        * Every other filter (EnKF, LETKF, sharded LETKF, local CSF, local transform CSF, EnSF,
          SF, reference): None.
      log_evidence: (K,) ``log p(y_k | y_1 .. y_{k-1})``, the data's log-likelihood one step at a
        time (0 at a step without an observed entry; a partly missing observation counts its
        observed entries), so ``log_evidence.sum()`` is ``log p(y_1 .. y_K)``; None from a
        filter that does not estimate it. What each estimate is (``csf_jax.evidence``):

        * the Kalman filter: exact;
        * the EnKF and the LETKF: the innovation density ``N(y; mean, C + R)`` of the forecast
          ensemble's predicted observations (sample covariance C), with the Gaussian stand-in of
          non-Gaussian noise or a ``Likelihood``: an approximation, exact as N grows for a
          linear-Gaussian model;
        * the particle filter: the log of the mean likelihood of its propagated particles, whose
          exponential is unbiased in ``p`` (the log is biased low);
        * CSF with the mixture prior (the default): the evidence of its particle and ensemble
          components, each one's prior weight times its importance-sampled evidence (the shock
          components, a jump the model lacks, left out: the model's own likelihood);
        * every other filter (CSF without the mixture, SF, EnSF, the local CSFs, the IEnKS, the
          sharded filters, the reference filter): None.

        The particle filter and CSF need the observation law's normalising constant
        (``ObservationNoise.log_norm`` / ``Likelihood.log_norm``, which every constructor gives);
        without it they return None. Steps from the first non-finite one on are NaN, like mean.
    """

    mean: jax.Array
    std: jax.Array
    ensembles: jax.Array | None = None
    ess: jax.Array | None = None
    finite: jax.Array | None = None
    info: dict | None = None
    log_evidence: jax.Array | None = None


def mark_nonfinite(result: FilterResult, obs) -> FilterResult:
    """Report non-finite steps of a filter run over ``obs (K, m)``; works under jit and vmap.

    A step is bad if its observation has an inf (NaN is a missing entry) or its mean or std a NaN
    or inf; a filter whose own state overflowed at a step (a forecast member or the ensemble's
    covariance non-finite: the model's drift blew up on a member) reports that step's mean as
    NaN, since resampling could drop the bad members and leave sane-looking numbers. From the
    first bad step on, ``finite`` is False and mean and std are NaN, so no filter (the particle
    filter's and the mixture's resampling can make later means finite again) returns plausible
    numbers after a bad input or a divergence. Ensembles and ESS are left as computed.

    What is not flagged: a mean or spread that is large but finite. No bound on it holds for
    every model: an unstable linear model seen through an outage grows its spread by
    ``|a|^K`` legitimately, stochastic volatility and Cauchy noise put members far out, so a
    threshold would refuse correct runs; the divergence rule stays the overflow of the state.
    """
    ok = (~jnp.isinf(obs).any(-1) & jnp.isfinite(result.mean).all(-1)
          & jnp.isfinite(result.std).all(-1))
    finite = jnp.cumsum(~ok) == 0
    nan = jnp.asarray(jnp.nan, result.mean.dtype)
    log_evidence = result.log_evidence
    if log_evidence is not None:
        log_evidence = jnp.where(finite, log_evidence, jnp.asarray(jnp.nan, log_evidence.dtype))
    return result._replace(mean=jnp.where(finite[:, None], result.mean, nan),
                           std=jnp.where(finite[:, None], result.std, nan), finite=finite,
                           log_evidence=log_evidence)
