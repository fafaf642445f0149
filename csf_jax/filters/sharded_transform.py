"""The transform-form local CSF with its sites split over devices, as the sharded LETKF.

The d sites of the ring are cut into P contiguous blocks of ``b = d / P`` sites, one per device
along the mesh axis ``"sites"`` (one host's devices, or several hosts' under
``jax.distributed.initialize``); the ensemble ``(N, d)`` lives as ``PartitionSpec(None,
"sites")``. Each filter step, inside one jitted ``lax.scan``: propagate and inflate (GSPMD, as
``csf_jax.filters.sharded``; the EnKF-N's factor of ``config.adaptive`` from all the sites'
innovations as one global computation), then ``local_transform.analysis`` with the mesh as its
``Ring``: the per-site work of each class of sites (windows, Levenberg-Marquardt steps,
eigendecompositions, the level steps) runs on each device's own block under ``jax.shard_map``,
with the window halos and the sensor states' overlaps exchanged with the ring neighbours
(``ppermute``), and the sensor ``model.observe`` runs on the full-length states as a global
computation (GSPMD). The per-site arithmetic is ``local_transform_filter``'s, so the results
equal it to float round-off.

What it filters (anything else is a ValueError at the boundary): the ring of
``ring_localization(d, sites)``; a time-invariant point sensor (observation j a function of site
``sites[j]`` alone), several observations of one site allowed; additive observation noise without
a covariance; ``d`` a multiple of P with a block at least as wide as the halo plus the class
count (``local_transform.transform_plan``).

Under several processes every process calls it with the same arguments (host arrays equal on all
processes, or global ``jax.Array``s); the result's arrays are global, sharded over the sites
(``sharded.gather_result`` brings them to every process).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from csf_jax import _checks
from csf_jax.filters.driver import Kernel, Method, run
from csf_jax.filters.letkf import Localization, require_localization
from csf_jax.filters.local_transform import (
    AXIS,
    CHUNK,
    LocalTransformConfig,
    Ring,
    analysis,
    site_obs,
    sites_observer,
    step_taper,
    transform_plan,
)
from csf_jax.filters.result import FilterResult, mark_nonfinite
from csf_jax.filters.sharded import (
    _check_arrays,
    _is_global,
    _place,
    _shares_a_cpu_pool,
    _state_sharding,
    check_mesh_model,
    check_ring,
    concrete_inputs,
    raise_if_diverged,
    require_host_obs,
    sharded_forecast,
)
from csf_jax.ssm import (
    StateSpaceModel,
    check_covariances,
    check_dynamics,
)

NAME = "sharded_transform_filter"


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3, 4, 5))
def _scan(model: StateSpaceModel, plan, mesh: Mesh, config: LocalTransformConfig, obs_info,
          return_ensembles: bool, inflation, y_sites, prec_sites, ensemble, key, index,
          has, obs=None) -> FilterResult:
    """The filter over ``y_sites (K, M, d)`` (each site's observations, NaN: none or missing)
    from ``ensemble (N, d)``, with ``prec_sites (M, d)`` their inverse variances; the key stream
    of ``csf_jax.local_transform_filter`` (``split(key, K)``). ``obs (K, m)``: the observations in
    their own order, for the EnKF-N's inflation (``config.adaptive``), computed over all the
    sites as one global computation. A step whose EnKF-N factor exceeds ``config.far_factor``
    is analysed at ``config.far_radius`` (``local_transform.step_taper``)."""
    dtype = ensemble.dtype
    state = _state_sharding(mesh, 2)
    ring = Ring(mesh, plan.devices)
    observe = sites_observer(model, obs_info, dtype, index, has,
                             lambda x: jax.lax.with_sharding_constraint(x, _state_sharding(mesh, 4)))

    def body(ens, xs):
        y, y_obs, key_k = xs
        forecast, factor = sharded_forecast(model, key_k, ens, inflation, state, y_obs,
                                            config.adaptive)
        taper, _ = step_taper(plan, config, factor)
        post = analysis(forecast, y, prec_sites, observe, plan, config, ring, taper)
        post = jax.lax.with_sharding_constraint(post, state)
        return post, (post.mean(0), post.std(0, ddof=1), post if return_ensembles else None)

    keys = jax.random.split(key, y_sites.shape[0])
    _, (mean, std, ensembles) = jax.lax.scan(body, ensemble, (y_sites, obs, keys))
    result = mark_nonfinite(FilterResult(mean=mean, std=std, ensembles=ensembles),
                            y_sites.reshape(y_sites.shape[0], -1))
    return result._replace(finite=jax.lax.with_sharding_constraint(
        result.finite, NamedSharding(mesh, P())))


@_checks.renamed_keywords(problem="model")
def sharded_transform_filter(obs, ensemble, *, model: StateSpaceModel, key,
                             localization: Localization,
                             config: LocalTransformConfig = LocalTransformConfig(),
                             mesh: Mesh | None = None, chunk: int = CHUNK,
                             return_ensembles: bool = False,
                             check_finite: bool = True) -> FilterResult:
    """Run the transform-form local CSF with the sites split over the devices of ``mesh``'s axis
    ``"sites"`` (module docstring).

    Args:
      obs: (K, m) observations; NaN marks a missing entry. A host array (the same on every
        process), or a global ``jax.Array`` for the identity sensor.
      ensemble: (N, d) at time 0; host or global array (placed as ``PartitionSpec(None,
        "sites")``).
      model: the model (static): time-invariant, a point sensor, i.i.d. additive noise.
      key: a ``jax.random.key`` (process noise only), the same on every process.
      localization: ``csf_jax.ring_localization(d, sites)``, sites[j] the site observation j reads.
      config: ``LocalTransformConfig``.
      mesh: a ``jax.sharding.Mesh`` with an axis ``"sites"``; None: ``site_mesh()``, every device
        of every process.
      chunk: as ``local_transform_filter``'s, per device block.
      return_ensembles: also return the (K, N, d) analysis ensembles.
      check_finite: raise FloatingPointError on a non-finite mean.
    Returns ``FilterResult(mean (K, d), std (K, d), ensembles (K, N, d) | None, finite (K,))``,
    equal to ``csf_jax.local_transform_filter``'s up to float round-off; the arrays are global,
    sharded over the sites (``gather_result`` for numpy copies on every process). Takes concrete
    arrays (it places them on the mesh), not tracers of an outer ``jax.jit``.
    """
    return run(method(localization, config, mesh=mesh, chunk=chunk), obs, ensemble, model=model,
               key=key, return_ensembles=return_ensembles, check_finite=check_finite)


def method(localization: Localization | None = None,
           config: LocalTransformConfig = LocalTransformConfig(), *, mesh: Mesh | None = None,
           chunk: int = CHUNK) -> Method:
    """The sharded transform CSF as a ``Method`` for ``csf_jax.run`` (arguments:
    ``sharded_transform_filter``); it runs its own scan on the mesh, so ``csf_jax.run`` takes
    concrete arrays for it."""
    localization = require_localization(localization, NAME)
    if not isinstance(config, LocalTransformConfig):
        raise TypeError(f"{NAME}: config must be a LocalTransformConfig, got "
                        f"{type(config).__name__}")
    return Method(SHARDED_TRANSFORM, (localization, config, mesh, chunk))


def _run_method(method, obs, ensemble, *, model, key, inputs=None, return_ensembles=False,
                check_finite=True, progress=None) -> FilterResult:
    localization, config, mesh, chunk, obs, ensemble = concrete_inputs(NAME, method, obs,
                                                                       ensemble, key, inputs)
    check_mesh_model(model, config, LocalTransformConfig, mesh, NAME,
                     "csf_jax.local_transform_filter", adaptive=True)
    info = site_obs(check_ring(model, localization, NAME), model.dim)

    plan = transform_plan(model.dim, float(config.radius), devices=int(mesh.shape[AXIS]),
                          slots=info.slots, chunk=chunk, one_by_one=_shares_a_cpu_pool(mesh),
                          name=NAME)
    _check_arrays(obs, ensemble, model, NAME)
    _checks.check_key(key, NAME)
    dtype = _checks.compute_dtype(jnp.result_type(obs), jnp.result_type(ensemble))
    check_covariances(model, dtype, NAME)
    check_dynamics(model, dtype, None, NAME)
    sites = _state_sharding(mesh, 2)
    prec = np.broadcast_to(1.0 / np.asarray(model.obs_noise.gaussian_std, np.float64) ** 2,
                           (model.obs_dim,))
    index = has = None
    if info.identity:
        prec_sites = prec[None]
        y_sites = obs[:, None] if _is_global(obs) else np.asarray(obs, dtype)[:, None]
    else:
        require_host_obs(NAME, obs)
        prec_sites = np.where(info.has, prec[info.index], 0.0)
        y_sites = np.where(info.has, np.asarray(obs, dtype)[:, info.index], np.nan)
        index, has = _place(info.index, sites, np.int32), _place(info.has, sites, bool)
    result = _scan(model, plan, mesh, dataclasses.replace(config, inflation=1.0),
                   info._replace(index=None, has=None),
                   bool(return_ensembles), jnp.asarray(config.inflation),
                   _place(y_sites, _state_sharding(mesh, 3), dtype),
                   _place(prec_sites, sites, dtype), _place(ensemble, sites, dtype), key, index,
                   has, _place(obs, NamedSharding(mesh, P()), dtype) if config.adaptive else None)
    if check_finite:
        raise_if_diverged(NAME, result)
    return result


SHARDED_TRANSFORM = Kernel(NAME, None, None, label="sharded transform CSF", runner=_run_method)
