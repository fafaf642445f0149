"""Input checks at the API boundary: shapes, dimensions and finiteness, with clear messages.

Shape checks run at trace time, so they also fire under ``jax.jit`` and ``jax.vmap``. Value checks
(NaN/inf) need concrete arrays and are skipped for tracers: inside a user's ``jit`` the caller owns
them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def is_concrete(*xs) -> bool:
    """True if no argument is a tracer (we are not inside jit/vmap/grad)."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs))


def check_finite(name: str, x, allow_nan: bool = False) -> None:
    """Raise ValueError naming the first non-finite entry of ``x`` (with ``allow_nan``: the first
    infinite one; NaN then means 'missing'); no-op for tracers."""
    if not is_concrete(x):
        return
    arr = np.asarray(x)
    if not np.issubdtype(arr.dtype, np.floating):
        return
    bad = np.isinf(arr) if allow_nan else ~np.isfinite(arr)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        what = "infinite value(s) (NaN marks a missing entry; inf is an error)" if allow_nan \
            else "non-finite value(s)"
        raise ValueError(f"{name} has {int(bad.sum())} {what}; first at index {idx}: "
                         f"{arr[idx]!r}")


def check_missing_supported(name: str, obs, model) -> None:
    """Refuse NaN (missing) observations for a noise that cannot marginalise them (no
    ``ObservationNoise.marginal``); no-op for tracers (there such steps come out non-finite). A
    ``Likelihood`` always can: its entries are independent given the state."""
    if getattr(model.obs_noise, "marginal", True) is not None or not is_concrete(obs):
        return
    if np.isnan(np.asarray(obs)).any():
        raise ValueError(f"{name}: obs has missing (NaN) entries, but the observation noise "
                         f"{model.obs_noise.name!r} has no marginal log-density to leave them out; "
                         f"give ObservationNoise(marginal=...) or use a noise built by csf_jax "
                         f"(gaussian_noise, gaussian_noise_cov, cauchy_noise)")


def check_obs(obs, model, *, name: str = "filter") -> tuple[int, int]:
    """Check ``obs (K, m)`` against ``model``: shape, float dtype, no inf (NaN: missing), and that
    the model's noise can leave missing entries out; return ``(K, m)``."""
    obs = jnp.asarray(obs)
    if obs.ndim != 2:
        raise ValueError(f"{name}: obs must have shape (K, m) = (steps, obs_dim), got {obs.shape}; "
                         f"use jax.vmap for batches of runs")
    K, m = obs.shape
    if m != model.obs_dim:
        raise ValueError(f"{name}: obs has dimension m={m} but model {model.name!r} has "
                         f"obs_dim={model.obs_dim}")
    if K < 1:
        raise ValueError(f"{name}: obs must hold at least one step, got shape {obs.shape}")
    if not jnp.issubdtype(obs.dtype, jnp.floating):
        raise TypeError(f"{name}: obs must be a floating array, got dtype {obs.dtype}")
    check_finite(f"{name}: obs", obs, allow_nan=True)
    check_missing_supported(name, obs, model)
    return K, m


def check_inputs(inputs, num_steps: int, model, *, name: str = "filter") -> None:
    """A time-varying model's per-step ``inputs``: a pytree of arrays with leading axis K (or
    None); refused for a model that is not time-varying."""
    if inputs is None:
        return
    if not model.time_varying:
        raise ValueError(f"{name}: inputs given, but model {model.name!r} is not time-varying "
                         f"(set time_varying=True and let drift/observe take the step)")
    for path, leaf in jax.tree_util.tree_leaves_with_path(inputs):
        shape = jnp.shape(leaf)
        if not shape or shape[0] != num_steps:
            where = jax.tree_util.keystr(path) or "inputs"
            raise ValueError(f"{name}: inputs{'' if where == 'inputs' else where} must have "
                             f"leading axis K={num_steps} (one input per observation), got shape "
                             f"{shape}")
        check_finite(f"{name}: inputs", leaf)


def check_filter_inputs(obs, ensemble, model, *, name: str = "filter") -> tuple[int, int, int, int]:
    """Check ``obs (K, m)`` and ``ensemble (N, d)`` against ``model``; return ``(K, m, N, d)``.

    NaN in ``obs`` means 'not observed' (per step and coordinate); inf in ``obs`` and any
    non-finite entry of ``ensemble`` are errors."""
    obs = jnp.asarray(obs)
    ensemble = jnp.asarray(ensemble)
    if obs.ndim != 2:
        raise ValueError(f"{name}: obs must have shape (K, m) = (steps, obs_dim), got {obs.shape}; "
                         f"use jax.vmap for batches of runs")
    if ensemble.ndim != 2:
        raise ValueError(f"{name}: ensemble must have shape (N, d) = (particles, dim), got "
                         f"{ensemble.shape}; use jax.vmap for batches of runs")
    K, m = obs.shape
    N, d = ensemble.shape
    if d != model.dim:
        raise ValueError(f"{name}: ensemble has dimension d={d} but model {model.name!r} has "
                         f"dim={model.dim}")
    if m != model.obs_dim:
        raise ValueError(f"{name}: obs has dimension m={m} but model {model.name!r} has "
                         f"obs_dim={model.obs_dim}")
    if K < 1:
        raise ValueError(f"{name}: obs must hold at least one step, got shape {obs.shape}")
    if N < 2:
        raise ValueError(f"{name}: ensemble needs at least 2 particles, got N={N}")
    for label, x in (("obs", obs), ("ensemble", ensemble)):
        if not jnp.issubdtype(x.dtype, jnp.floating):
            raise TypeError(f"{name}: {label} must be a floating array, got dtype {x.dtype}")
        check_finite(f"{name}: {label}", x, allow_nan=label == "obs")
    check_missing_supported(name, obs, model)
    return K, m, N, d


def check_key(key, name: str = "filter") -> None:
    """Require a JAX PRNG key (typed ``jax.random.key`` or legacy uint32 ``(2,)``)."""
    if key is None:
        raise TypeError(f"{name}: key= is required (e.g. key=jax.random.key(0)); "
                        f"there is no global RNG")
    if jnp.issubdtype(jnp.asarray(key).dtype if not hasattr(key, "dtype") else key.dtype,
                      jax.dtypes.prng_key):
        if jnp.shape(key) != ():
            raise ValueError(f"{name}: key must be a single key, got shape {jnp.shape(key)}")
        return
    if jnp.shape(key) != (2,) or jnp.asarray(key).dtype != jnp.uint32:
        raise TypeError(f"{name}: key must be a jax.random.key, got {type(key).__name__} with "
                        f"shape {jnp.shape(key)}")


def check_result_finite(name: str, result) -> None:
    """After a concrete run: raise FloatingPointError at the first step whose mean is non-finite."""
    if not is_concrete(result.mean):
        return
    mean = np.asarray(result.mean)
    bad = ~np.isfinite(mean).all(axis=-1)
    if bad.any():
        k = int(np.argmax(bad))
        raise FloatingPointError(
            f"{name}: the filtered mean became non-finite at step {k + 1} of {mean.shape[0]} "
            f"(the ensemble diverged). Check the model's drift for blow-up and, for CSF, use the "
            f"stable guidance (GuidanceConfig(mode='clipped')); pass check_finite=False to get the "
            f"raw result instead.")


def promote(obs, ensemble):
    """``obs (K, m)`` and ``ensemble (N, d)`` as arrays of their common float dtype
    (``jnp.result_type``: a float16 ensemble with float32 obs runs in float32; float64 obs with a
    float32 ensemble in float64 under x64). Inputs are already checked to be floating."""
    obs, ensemble = jnp.asarray(obs), jnp.asarray(ensemble)
    dtype = jnp.result_type(obs.dtype, ensemble.dtype)
    return obs.astype(dtype), ensemble.astype(dtype)


def promote_tree(obs, state):
    """``obs`` and every floating leaf of ``state`` (an ensemble, or a filter's initial state) as
    arrays of their common float dtype (as ``promote``)."""
    obs = jnp.asarray(obs)
    leaves = [jnp.asarray(x) for x in jax.tree_util.tree_leaves(state)]
    dtype = jnp.result_type(obs.dtype, *[x.dtype for x in leaves
                                         if jnp.issubdtype(x.dtype, jnp.floating)])
    cast = lambda x: (jnp.asarray(x).astype(dtype)
                      if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating) else jnp.asarray(x))
    return obs.astype(dtype), jax.tree_util.tree_map(cast, state)


def check_sigma_max(network, config, name: str) -> None:
    """A learned score net is trained for one VE SDE scale: the sampler must use the same."""
    if network.sigma_max != config.sigma_max:
        raise ValueError(f"{name}: the network config has sigma_max={network.sigma_max}, but the "
                         f"sampler's config.sigma_max={config.sigma_max}; they must agree")
