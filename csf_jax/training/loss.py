"""Conditional denoising score matching (paper Eq. cond_score_matching, Alg. 1).

For a prior ensemble S, its code ``c = encoder(S)``, targets ``x0 ~ S``, ``t ~ U(t_min, 1)`` and
``z ~ N(0, I)``: ``x_t = x0 + sigma_t z`` and the loss is ``|| sigma_t s(x_t, t; c) + z ||^2``.
Beyond Alg. 1, one encoder pass serves ``T`` targets of the same set.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from csf_jax import networks
from csf_jax.sde import marginal_std


def set_loss(params, config: networks.NetworkConfig, subset, x0, t, z):
    """Loss of one set. ``subset: (n, d)`` the encoded particles; ``x0, z: (T, d)``; ``t: (T,)``."""
    code = networks.encode(params, subset, config)
    sigma = marginal_std(t, config.sigma_max)[:, None]
    s = networks.score(params, x0 + sigma * z, t, code, config)
    return jnp.mean(jnp.sum((sigma * s + z) ** 2, axis=-1))


def batch_loss(params, config: networks.NetworkConfig, subsets, x0, t, z):
    """Mean of ``set_loss`` over a batch: ``subsets (B, n, d)``, ``x0, z (B, T, d)``, ``t (B, T)``."""
    losses = jax.vmap(set_loss, in_axes=(None, None, 0, 0, 0, 0))(params, config, subsets, x0, t, z)
    return jnp.mean(losses)


def draw_noise(key, shape_bt: tuple, dim: int, t_min: float):
    """``t ~ U(t_min, 1)`` of shape ``(B, T)`` and ``z ~ N(0, I)`` of shape ``(B, T, d)``."""
    k_t, k_z = jax.random.split(key)
    t = jax.random.uniform(k_t, shape_bt, minval=t_min, maxval=1.0)
    return t, jax.random.normal(k_z, shape_bt + (dim,))
