"""Conditional denoising score matching (paper Eq. cond_score_matching, Alg. 1).

For a prior ensemble S, its code ``c = encoder(S)``, targets ``x0 ~ S``, ``t ~ U(t_min, 1)`` and
``z ~ N(0, I)``: ``x_t = x0 + sigma_t z`` and the loss is ``|| sigma_t s(x_t, t; c) + z ||^2``.
Beyond Alg. 1, one encoder pass serves ``T`` targets of the same set.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from csf_jax import _random, networks
from csf_jax.prior import ResidualContext, ensemble_moments, residual_score
from csf_jax.sde import marginal_std


def set_loss(params, config: networks.NetworkConfig, subset, x0, t, z, full=None):
    """Loss of one set. ``subset: (n, d)`` the encoded particles; ``x0, z: (T, d)``; ``t: (T,)``.

    full: ``(M, d)`` the whole stored ensemble the subset and targets come from; the Gaussian base
    of a ``base="gaussian"`` network takes its moments from it (as the filter does from all N).
    """
    sigma = marginal_std(t, config.sigma_max)[:, None]
    xt = x0 + sigma * z
    code = networks.encode(params, subset, config)
    if config.base == "gaussian":
        ctx = ResidualContext(code, ensemble_moments(subset if full is None else full))
        s = residual_score(params, config, ctx, xt, t)
    else:
        s = networks.score(params, xt, t, code, config)
    return jnp.mean(jnp.sum((sigma * s + z) ** 2, axis=-1))


def batch_loss(params, config: networks.NetworkConfig, subsets, x0, t, z, full=None):
    """Mean of ``set_loss`` over a batch: ``subsets (B, n, d)``, ``x0, z (B, T, d)``, ``t (B, T)``,
    ``full (B, M, d)`` or None."""
    losses = jax.vmap(set_loss, in_axes=(None, None, 0, 0, 0, 0, 0 if full is not None else None))(
        params, config, subsets, x0, t, z, full)
    return jnp.mean(losses)


def draw_noise(key, shape_bt: tuple, dim: int, t_min: float):
    """``t ~ U(t_min, 1)`` of shape ``(B, T)`` and ``z ~ N(0, I)`` of shape ``(B, T, d)``."""
    k_t, k_z = jax.random.split(key)
    t = jax.random.uniform(k_t, shape_bt, minval=t_min, maxval=1.0)
    return t, _random.normal(k_z, shape_bt + (dim,))
