"""One branch for every run of a ``jax.vmap``: ``batch_max``.

Under ``jax.vmap`` a ``lax.cond`` or ``lax.switch`` whose index differs between the runs becomes a
select: every branch runs for every run. CSF's step picks its work by an index (no ensemble member
of a kind: skip its draws; a few: draw for a block of them), and most steps need the cheap branch,
so a vmapped pair of runs would pay for all of them. ``batch_max(index)`` gives the runs one
index, the largest, unbatched: the switch stays a switch and runs the branch that serves all of
them. The branches must agree wherever they all apply (the callers' are the same draws computed
for more members than needed), so a vmapped call gives what separate calls give.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


@jax.custom_batching.custom_vmap
def batch_max(index: jax.Array) -> jax.Array:
    """``index`` (a scalar) outside ``jax.vmap``; under it the largest over the mapped runs,
    the same (unbatched) for all of them. Nested maps reduce at every level."""
    return index


@batch_max.def_vmap
def _batch_max_rule(axis_size, in_batched, index):
    del axis_size
    (batched,) = in_batched
    return batch_max(jnp.max(index) if batched else index), False
