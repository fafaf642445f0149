"""Fit an unconditional diffusion model to ONE ensemble (denoising score matching, no encoder).

The from-scratch reference of the prior-quality study (paper Fig. 2b/3a) and the per-step training
of the score-based filter (SF) baseline. A fit is one ``lax.scan`` over Adam steps; only the score
net's variables are trained (the code is fixed at zero, the encoder is unused). A core module: the
SF filter uses it online, so it sits below both ``csf_jax.filters`` and ``csf_jax.training``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax

from csf_jax import _random, networks
from csf_jax.sde import marginal_std


def dsm_fit(key, ensemble, score_vars, opt_state, optimizer: optax.GradientTransformation, *,
            config: networks.NetworkConfig, steps: int, batch: int, t_min: float = 1e-3,
            shards: int = 1):
    """``steps`` Adam steps of unconditional DSM of ``score_vars`` on ``ensemble (N, d)``.

    Pure and jit/vmap-able. Each step draws ``batch`` particles with replacement, times
    ``t ~ U(t_min, 1)`` and noises; loss ``|sigma_t s(x0 + sigma_t z, t) + z|^2``.
    shards > 1: each step's loss and gradient are computed data-parallel, the batch split over the
    first ``shards`` local devices (``jax.shard_map``, gradients averaged with ``pmean``): the same
    draws and the same update up to float summation order, for one fit on several devices (one
    XLA host device per CPU core: a training batch through this small net does not keep several
    cores busy on its own; docs/design.md).

    Returns ``(score_vars, opt_state, losses (steps,))``.
    """
    code = jnp.zeros((config.code_dim,), ensemble.dtype)

    def loss_fn(sv, x0, t, z):
        sigma = marginal_std(t, config.sigma_max)[:, None]
        s = networks.ScoreNet(config).apply(sv, x0 + sigma * z, t, code)
        return jnp.mean(jnp.sum((sigma * s + z) ** 2, axis=-1))

    value_and_grad = _data_parallel(jax.value_and_grad(loss_fn), shards, batch)

    def step(carry, k):
        sv, o = carry
        k_i, k_t, k_z = jax.random.split(k, 3)
        x0 = ensemble[jax.random.randint(k_i, (batch,), 0, ensemble.shape[0])]
        t = jax.random.uniform(k_t, (batch,), ensemble.dtype, minval=t_min, maxval=1.0)
        z = _random.normal(k_z, x0.shape, x0.dtype)
        loss, g = value_and_grad(sv, x0, t, z)
        updates, o = optimizer.update(g, o, sv)
        return (optax.apply_updates(sv, updates), o), loss

    (score_vars, opt_state), losses = jax.lax.scan(step, (score_vars, opt_state),
                                                   jax.random.split(key, steps))
    return score_vars, opt_state, losses


def _data_parallel(value_and_grad, shards: int, batch: int):
    """``value_and_grad(sv, x0, t, z)`` of a batch-mean loss, with the batch axis split over
    ``shards`` local devices and the shards' means averaged (``shards`` 1: itself)."""
    if shards == 1:
        return value_and_grad
    devices = jax.local_devices()
    if shards > len(devices) or batch % shards:
        raise ValueError(f"dsm_fit: shards={shards} needs that many local devices (have "
                         f"{len(devices)}) and must divide the batch ({batch})")
    mesh = jax.sharding.Mesh(np.array(devices[:shards]), ("batch",))
    P = jax.sharding.PartitionSpec

    def shard(sv, x0, t, z):
        return jax.lax.pmean(value_and_grad(sv, x0, t, z), "batch")

    return jax.shard_map(shard, mesh=mesh, in_specs=(P(), P("batch"), P("batch"), P("batch")),
                         out_specs=P(), check_vma=False)


@functools.partial(jax.jit, static_argnames=("config", "steps", "batch", "lr", "t_min"))
def fit_unconditional(key, ensemble, params, *, config: networks.NetworkConfig, steps: int = 1000,
                      batch: int = 256, lr: float = 2e-3, t_min: float = 1e-3):
    """Train the score net of ``params`` (code fixed at zero) on ``ensemble (N, d)`` with fresh Adam.

    Returns ``(params, losses (steps,))``; ``params["encoder"]`` is passed through untouched. Pass
    fresh ``networks.init_params`` output, or a previous fit to warm-start.
    """
    opt = optax.adam(lr)
    score_vars, _, losses = dsm_fit(key, ensemble, params["score"], opt.init(params["score"]), opt,
                                    config=config, steps=steps, batch=batch, t_min=t_min)
    return {**params, "score": score_vars}, losses
