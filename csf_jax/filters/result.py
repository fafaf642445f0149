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
      ess: (K,) effective sample size before resampling (particle filter only), else None.
      finite: (K,) bool, False from the first step whose observation is infinite or whose mean or
        std is non-finite on; mean and std are NaN there (``mark_nonfinite``). NaN observations
        are missing, not bad. Concrete calls refuse infinite observations and raise on a
        non-finite mean (``check_finite=True``), so this matters under ``jax.jit``/``jax.vmap``.
        None only for results built by hand.
      info: dict of per-step diagnostics ``(K,)``, or None: CSF's ``bandwidth`` (the kernel
        bandwidth h of its mixture prior, 1 = the ensemble's Gaussian) and ``shock_weight`` (the
        posterior weight of the broad shock component).
    """

    mean: jax.Array
    std: jax.Array
    ensembles: jax.Array | None = None
    ess: jax.Array | None = None
    finite: jax.Array | None = None
    info: dict | None = None


def mark_nonfinite(result: FilterResult, obs) -> FilterResult:
    """Report non-finite steps of a filter run over ``obs (K, m)``; works under jit and vmap.

    A step is bad if its observation has an inf (NaN is a missing entry) or its mean or std a NaN
    or inf. From the first bad step on,
    ``finite`` is False and mean and std are NaN, so no filter (the particle filter's resampling
    can make later means finite again) returns plausible numbers after a bad input. Ensembles and
    ESS are left as computed.
    """
    ok = (~jnp.isinf(obs).any(-1) & jnp.isfinite(result.mean).all(-1)
          & jnp.isfinite(result.std).all(-1))
    finite = jnp.cumsum(~ok) == 0
    nan = jnp.asarray(jnp.nan, result.mean.dtype)
    return result._replace(mean=jnp.where(finite[:, None], result.mean, nan),
                           std=jnp.where(finite[:, None], result.std, nan), finite=finite)
