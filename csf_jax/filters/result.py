"""The result type shared by every filter (CSF, SF, PF, EnKF, Kalman)."""

from __future__ import annotations

from typing import NamedTuple, Optional

import jax


class FilterResult(NamedTuple):
    """What a filter returns; a pytree, so ``jax.vmap`` over runs batches every field.

    Attributes:
      mean: (K, d) filtered mean of ``x_k`` given ``y_1 .. y_k``, for k = 1 .. K.
      std: (K, d) per-coordinate spread (ensemble or posterior std).
      ensembles: (K, N, d) posterior ensembles, or None unless ``return_ensembles=True``
        (the Kalman filter has no ensemble and always returns None).
      ess: (K,) effective sample size before resampling (particle filter only), else None.
    """

    mean: jax.Array
    std: jax.Array
    ensembles: Optional[jax.Array] = None
    ess: Optional[jax.Array] = None
