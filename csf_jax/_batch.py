"""What ``jax.vmap`` does to a filter's runs: ``batch_max`` (one branch for every run) and
``one_at_a_time`` (a vmapped run is the run of a separate call).

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


def one_at_a_time(fn):
    """``fn`` whose ``jax.vmap`` runs the mapped calls one after another (``lax.map``), each the
    very program of a separate call, instead of one batched program.

    A filter's run turns float rounding into different numbers when it is batched: a batched
    reduction or product rounds differently in the last bit, and a resampling index, a line
    search's pick or a quantile's member can flip on it, after which the runs part. Mapped one
    at a time, ``jax.vmap`` of a run gives what separate calls with the same keys give, bit for
    bit, at the cost of the parallelism over runs (the members of one run are still batched). Arguments and results are pytrees;
    unbatched arguments are shared by every call; nested maps apply the rule at every level.
    Not differentiable in reverse mode (a ``custom_vmap``), so the driver maps this way only the
    filters whose runs have discrete choices (``Kernel.discrete``), none of them differentiated.
    """
    mapped = jax.custom_batching.custom_vmap(fn)

    @mapped.def_vmap
    def _rule(axis_size, in_batched, *args):
        del axis_size
        leaves, tree = jax.tree_util.tree_flatten(args)
        flags = jax.tree_util.tree_leaves(in_batched)
        batched = [leaf for leaf, b in zip(leaves, flags) if b]

        def one(slices):
            it = iter(slices)
            full = [next(it) if b else leaf for leaf, b in zip(leaves, flags)]
            return mapped(*jax.tree_util.tree_unflatten(tree, full))

        out = jax.lax.map(one, batched)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return mapped
