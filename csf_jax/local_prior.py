"""The local CSF's prior: a sparse Gaussian (a Gaussian Markov random field) estimated from local
regressions of the ensemble, so that cost and memory are linear in d.

Every site i is regressed on its predecessors ``pred(i)``: the sites ``j < i`` within ring distance
b (the modified-Cholesky estimate of a banded precision; Ueno & Nakamura 2016, Nino-Ruiz et al.
2018):

    x_i - m_i = sum_{j in pred(i)} beta_ij (x_j - m_j) + e_i,    e_i ~ N(0, D_i)

so that the prior precision is ``Lambda = (I - B)^T D^{-1} (I - B)`` with B strictly lower triangular:
symmetric positive definite by construction, sparse (O(d b) entries), estimated from ``O(N d b^2)``
work, and a product ``Lambda v`` costs ``O(d b)``. The sampler never forms it.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _linalg, _random


@functools.lru_cache(maxsize=32)
def ring_predecessors(dim: int, half_width: int) -> tuple:
    """``(index (d, 2b) int32, valid (d, 2b) bool)``: site i's predecessors, the sites ``j < i``
    within ring distance b (padded with i itself, invalid). Site ``d - 1`` has 2b of them (the ring
    closes through them), site 0 none."""
    if not 1 <= half_width or 2 * half_width + 1 > dim:
        raise ValueError(f"a neighbourhood of half-width {half_width} does not fit a ring of "
                         f"{dim} sites")
    offsets = np.concatenate([-np.arange(1, half_width + 1), np.arange(1, half_width + 1)])
    site = np.arange(dim)[:, None]
    cand = (site + offsets[None, :]) % dim
    valid = cand < site
    index = np.where(valid, cand, site).astype(np.int32)
    index.setflags(write=False)
    valid.setflags(write=False)
    return index, valid


class LocalStats(NamedTuple):
    """The propagated ensemble's local statistics: what the local prior is conditioned on.

    mean: (d,).  pred: (d, P) predecessor sites.  coef: (d, P) regression coefficients ``beta``
    (0 on padding).  dinv: (d,) ``1 / D_i``.
    """

    mean: jax.Array
    pred: jax.Array
    coef: jax.Array
    dinv: jax.Array


def local_statistics(ensemble, half_width: int, ridge: float = 1e-2,
                     floor: float = 1e-3) -> LocalStats:
    """``LocalStats`` of ``ensemble (N, d)``: regressions on predecessors within ring distance
    ``half_width``.

    ridge: Tikhonov term on the regressions, times the predecessors' variances (shrinks the
      coefficients a small ensemble overfits).  floor: ``D_i`` is kept above ``floor`` times the
      site's variance. ``D_i`` is the residual variance with ``N - 1 - P_i`` degrees of freedom.
    """
    n, d = ensemble.shape
    pred_np, valid_np = ring_predecessors(d, half_width)
    pred, valid = jnp.asarray(pred_np), jnp.asarray(valid_np)
    mean = ensemble.mean(0)
    centred = ensemble - mean
    var = jnp.sum(centred ** 2, 0) / max(n - 1, 1)
    xp = centred[:, pred] * valid                                        # (N, d, P)
    cpp = jnp.einsum("ndp,ndq->dpq", xp, xp) / max(n - 1, 1)
    cpi = jnp.einsum("ndp,nd->dp", xp, centred) / max(n - 1, 1)
    diag = jnp.where(valid, var[pred] * (1.0 + ridge), 1.0)
    cpp = cpp * (1.0 - jnp.eye(pred.shape[1], dtype=cpp.dtype)) + jax.vmap(jnp.diag)(diag)
    coef = _linalg.cho_solve(_linalg.cholesky(cpp), cpi) * valid
    dof = jnp.maximum(n - 1 - valid.sum(1), 1).astype(ensemble.dtype)
    resid = jnp.sum((centred - jnp.einsum("dp,ndp->nd", coef, xp)) ** 2, 0) / dof
    tiny = jnp.finfo(ensemble.dtype).tiny ** 0.5
    dinv = 1.0 / jnp.maximum(resid, floor * var + tiny)
    return LocalStats(mean, pred, coef, dinv)


def apply_l(stats: LocalStats, v):
    """``(I - B) v`` for ``v (..., d)``."""
    return v - jnp.sum(stats.coef * v[..., stats.pred], -1)


def apply_lt(stats: LocalStats, r):
    """``(I - B)^T r`` for ``r (..., d)`` (a scatter-add onto the predecessors)."""
    contrib = stats.coef * r[..., :, None]                                # (..., d, P)
    return r - jnp.zeros_like(r).at[..., stats.pred].add(contrib)


def precision_matvec(stats: LocalStats, v):
    """``Lambda v = (I - B)^T D^{-1} (I - B) v`` for ``v (..., d)``."""
    return apply_lt(stats, stats.dinv * apply_l(stats, v))


def precision_diagonal(stats: LocalStats):
    """``(d,)``: the diagonal of ``Lambda``."""
    sq = stats.coef ** 2 * stats.dinv[:, None]
    return stats.dinv + jnp.zeros_like(stats.dinv).at[stats.pred].add(sq)


def precision_noise(stats: LocalStats, key, shape, dtype):
    """A draw of ``N(0, Lambda)`` of shape ``shape (..., d)``: ``(I - B)^T D^{-1/2} eps``."""
    return apply_lt(stats, jnp.sqrt(stats.dinv) * _random.normal(key, shape, dtype))


def dense_precision(stats: LocalStats):
    """``(d, d)`` ``Lambda`` (tests and small d only)."""
    return jax.vmap(lambda e: precision_matvec(stats, e))(jnp.eye(stats.mean.shape[0],
                                                                 dtype=stats.mean.dtype))


def precision_blocks(stats: LocalStats, block: int):
    """``(d / block, block, block)``: the diagonal blocks of ``Lambda`` on consecutive runs of
    ``block`` sites, by probing: ``Lambda`` couples sites at most ``2b`` apart on the ring, so with
    ``block > 2b`` and an even number of blocks, one probe per position and block parity reads every
    block's columns without contamination (2 x block products with ``Lambda``)."""
    d = stats.mean.shape[0]
    nb = d // block
    parity = (jnp.arange(d) // block) % 2
    position = jnp.arange(d) % block
    probes = ((parity[None, None, :] == jnp.arange(2)[:, None, None])
              & (position[None, None, :] == jnp.arange(block)[None, :, None])).astype(
        stats.mean.dtype)                                                   # (2, block, d)
    cols = precision_matvec(stats, probes).reshape(2, block, nb, block)      # (parity, q, J, p)
    own = jnp.where((jnp.arange(nb) % 2)[None, None, :, None] == jnp.arange(2)[:, None, None, None],
                    cols, 0.0).sum(0)                                       # (q, J, p)
    return jnp.transpose(own, (1, 2, 0))                                    # (J, p, q)
