"""Fit an unconditional diffusion model to ONE ensemble (denoising score matching, no encoder).

The from-scratch reference of the prior-quality study (paper Fig. 2b/3a) and the per-step training
of the score-based filter baseline. The whole fit is one jitted ``lax.scan`` over optimizer steps.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import optax

from csf_jax import networks
from csf_jax.sde import marginal_std


@functools.partial(jax.jit, static_argnames=("config", "steps", "batch", "lr", "t_min"))
def fit_unconditional(key, ensemble, params, *, config: networks.NetworkConfig, steps: int = 1000,
                      batch: int = 256, lr: float = 2e-3, t_min: float = 1e-3):
    """Train the score net of ``params`` (code fixed at zero) on ``ensemble (N, d)``.

    Returns ``(params, losses (steps,))``. Pass fresh ``networks.init_params`` output, or the
    previous fit to warm-start.
    """
    opt = optax.adam(lr)
    code = jnp.zeros((config.code_dim,), ensemble.dtype)

    def loss_fn(p, x0, t, z):
        sigma = marginal_std(t, config.sigma_max)[:, None]
        s = networks.score(p, x0 + sigma * z, t, code, config)
        return jnp.mean(jnp.sum((sigma * s + z) ** 2, axis=-1))

    def step(carry, k):
        p, o = carry
        k_i, k_t, k_z = jax.random.split(k, 3)
        x0 = ensemble[jax.random.randint(k_i, (batch,), 0, ensemble.shape[0])]
        t = jax.random.uniform(k_t, (batch,), minval=t_min, maxval=1.0)
        z = jax.random.normal(k_z, x0.shape, x0.dtype)
        loss, g = jax.value_and_grad(loss_fn)(p, x0, t, z)
        updates, o = opt.update(g, o, p)
        return (optax.apply_updates(p, updates), o), loss

    (params, _), losses = jax.lax.scan(step, (params, opt.init(params)),
                                       jax.random.split(key, steps))
    return params, losses
