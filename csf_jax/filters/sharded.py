"""The LETKF with its state sites split over devices: a ``jax.sharding.Mesh`` axis ``"sites"``.

The d sites of the ring are cut into P contiguous blocks of ``b = d / P`` sites, one block per
device along the mesh axis ``"sites"`` (P devices of one host, or of several hosts joined by
``jax.distributed.initialize``). The ensemble ``(N, d)`` lives sharded as
``PartitionSpec(None, "sites")``: every device holds all N members of its own b sites. Each filter
step, inside one jitted ``lax.scan``:

    propagate (GSPMD: the model's drift on the global array; XLA inserts the neighbour exchanges
      that Lorenz-96's x[i-2], x[i-1], x[i+1] need) -> inflate -> predicted observations h(x)
      (GSPMD) -> per block (``jax.shard_map``): anomalies, innovations and observation weights of
      its own sites, a ring halo of ``h`` sites from the left and right neighbours
      (``jax.lax.ppermute``), and the LETKF transform of each of its sites -> mean and std.

The halo width ``h`` is the number of sites on one side of a site whose observations are in reach
(Gaspari-Cohn taper > 0: distance < 2 radius); it must not exceed b (one hop). The analysis of a
site is ``csf_jax.filters.letkf.letkf_analysis``'s, with the site's observations taken from the
window of ``2 h + 1`` sites around it, so the results equal ``csf_jax.letkf``'s up to float
round-off (sums over the window in another order). A device analyses its sites ``chunk`` at a time
(``SitePlan.chunk``), which bounds the analysis's memory whatever d.

What it filters (anything else is a ValueError at the boundary): the ring
localisation of ``ring_localization(d, sites)``; a time-invariant point sensor (observation j a
function of site ``sites[j]`` alone: identity, arctan, every k-th site), at most one observation
per site; additive observation noise without a covariance (i.i.d., as the LETKF needs); ``d``
a multiple of P.

Under several processes every process calls ``sharded_letkf`` with the same arguments (host arrays
equal on all processes, or global ``jax.Array``s); the result's arrays are global, sharded over
the sites; ``gather_result`` brings them to every process as numpy arrays.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from csf_jax import _checks
from csf_jax.covariance import gaspari_cohn
from csf_jax.filters.driver import Kernel, Method, run
from csf_jax.filters.letkf import (
    LETKFConfig,
    Localization,
    _model_sensor_sites,
    enkf_n_inflation,
    require_localization,
)
from csf_jax.filters.result import FilterResult, mark_nonfinite
from csf_jax.ssm import (
    StateSpaceModel,
    check_covariances,
    check_dynamics,
    check_model,
    is_additive,
    observed,
    propagate,
)

AXIS = "sites"
NAME = "sharded_letkf"
#: the most sites a device analyses at once (``SitePlan.chunk``): the analysis's working memory
#: grows linearly with the chunk (and as N^2 per site); its size at N = 20, radius 4 is on
#: docs/scale_out.md, "Memory per device"
CHUNK = 2 ** 16


class SitePlan(NamedTuple):
    """How the ring of ``dim`` sites is cut (static, hashable).

    dim: d.  devices: P, the blocks.  block: b = d / P sites per device.  halo: h, the sites on each
    side of a site whose observations are in reach.  offsets: ``(2h + 1,)`` the window's site
    offsets, in the order the LETKF sorts a site's observations (0, -1, +1, -2, +2, ...).
    taper: ``(2h + 1,)`` the Gaspari-Cohn weight at each offset.  chunk: sites analysed at once
    (a divisor of b; the chunks of a block one after the other), which bounds the analysis's
    working memory (linear in the chunk, growing as N^2 per site: the N x N matrices of each site;
    measured on docs/scale_out.md).  one_by_one:
    eigendecompose the sites one at a time (``site_transform``), for CPU meshes with several
    devices in one process.
    """

    dim: int
    devices: int
    block: int
    halo: int
    offsets: tuple
    taper: tuple
    chunk: int
    one_by_one: bool = False


class SiteSlots(NamedTuple):
    """Where the observations sit on the sites (a point sensor, at most one per site).

    identity: observation j reads site j and m = d (no re-indexing).  index: ``(d,)`` int32, the
    observation at each site (0 where none).  has: ``(d,)`` bool, whether the site has one.
    """

    identity: bool
    index: np.ndarray | None
    has: np.ndarray | None


def halo_width(radius: float) -> int:
    """The sites on one side of a site whose observations get a positive taper: the largest
    integer offset ``o`` with ``gaspari_cohn(o / radius) > 0`` (0 if none), as ``local_obs``
    counts them."""
    reach = np.arange(1, int(np.ceil(2.0 * radius)) + 1)
    inside = reach[gaspari_cohn(reach / radius) > 0]
    return int(inside.max()) if inside.size else 0


def site_plan(dim: int, radius: float, devices: int, *, chunk: int = CHUNK,
              one_by_one: bool = False) -> SitePlan:
    """The ``SitePlan`` of ``dim`` ring sites over ``devices`` blocks at localisation half-width
    ``radius``; ``chunk``: at most that many sites analysed at once (the largest divisor of the
    block not above it); ``one_by_one``: as ``SitePlan``. ValueError if ``devices`` does not
    divide ``dim``, if the halo is wider than a block, or if the window of ``2 h + 1`` sites is
    wider than the ring."""
    if dim % devices:
        raise ValueError(f"{NAME}: d={dim} is not a multiple of the {devices} devices of the mesh "
                         f"axis {AXIS!r}; each device takes an equal block of sites (choose d or "
                         f"the device count so that it divides)")
    block = dim // devices
    halo = halo_width(radius)
    if 2 * halo + 1 > dim:
        raise ValueError(f"{NAME}: the localisation window ({2 * halo + 1} sites at radius "
                         f"{radius:g}) is wider than the ring (d={dim}); use a smaller radius")
    if halo > block:
        raise ValueError(f"{NAME}: the halo ({halo} sites on each side at radius {radius:g}) is "
                         f"wider than a device's block ({block} sites = d {dim} / {devices} "
                         f"devices); use fewer devices, a larger d or a smaller radius")
    offsets = [0] + [s * o for o in range(1, halo + 1) for s in (-1, 1)]
    taper = gaspari_cohn(np.abs(np.asarray(offsets, np.float64)) / radius)
    return SitePlan(dim, devices, block, halo, tuple(offsets), tuple(float(t) for t in taper),
                    largest_divisor(block, chunk), bool(one_by_one))


def largest_divisor(n: int, cap: int) -> int:
    """The largest divisor of ``n`` that is at most ``cap`` (at least 1)."""
    if isinstance(cap, bool) or not isinstance(cap, (int, np.integer)) or cap < 1:
        raise ValueError(f"{NAME}: chunk must be a positive int, got {cap!r}")
    best = 1
    for k in range(1, int(np.sqrt(n)) + 1):
        if n % k == 0:
            best = max([best] + [v for v in (k, n // k) if v <= cap])
    return best


def site_slots(sites: np.ndarray, dim: int) -> SiteSlots:
    """The ``SiteSlots`` of a point sensor whose observation j reads site ``sites[j]``;
    ValueError if two observations read one site."""
    sites = np.asarray(sites, np.int64)
    if np.unique(sites).size != sites.size:
        site = int(np.flatnonzero(np.bincount(sites, minlength=dim) > 1)[0])
        raise ValueError(f"{NAME}: at most one observation per site, but site {site} has "
                         f"{int(np.sum(sites == site))}")
    if sites.size == dim and np.array_equal(sites, np.arange(dim)):
        return SiteSlots(True, None, None)
    index = np.zeros(dim, np.int32)
    index[sites] = np.arange(sites.size, dtype=np.int32)
    has = np.zeros(dim, bool)
    has[sites] = True
    return SiteSlots(False, index, has)


def site_mesh(devices=None) -> Mesh:
    """A 1-D mesh with the axis ``"sites"`` over ``devices`` (default ``jax.devices()``: every
    device of every process, so it spans the hosts under ``jax.distributed``). TypeError for
    anything but a sequence of ``jax.Device``s (a string such as a platform name), ValueError for
    an empty one."""
    if devices is None:
        devices = jax.devices()
    elif isinstance(devices, (str, bytes)) or not hasattr(devices, "__iter__"):
        raise TypeError(f"site_mesh: devices must be a sequence of jax devices (e.g. "
                        f"jax.devices()[:2]), got {type(devices).__name__} {devices!r:.40}")
    devices = list(devices)
    if not devices:
        raise ValueError("site_mesh: devices is empty; give at least one jax device (e.g. "
                        "jax.devices()[:2]) or None for all of them")
    wrong = [d for d in devices if not isinstance(d, jax.Device)]
    if wrong:
        raise TypeError(f"site_mesh: devices must be jax devices (e.g. jax.devices()[:2]), got "
                        f"{type(wrong[0]).__name__} {wrong[0]!r:.40}")
    return Mesh(np.asarray(devices), (AXIS,))


def ring_halo(block, halo: int, devices: int):
    """Inside ``shard_map`` over ``"sites"``: ``block (..., b)`` extended to ``(..., b + 2 halo)``
    by the last ``halo`` sites of the left neighbour's block and the first ``halo`` of the right
    neighbour's (device ``P - 1`` is device 0's left neighbour: the ring)."""
    if halo == 0:
        return block
    to_right = [(i, (i + 1) % devices) for i in range(devices)]
    to_left = [(i, (i - 1) % devices) for i in range(devices)]
    left = jax.lax.ppermute(block[..., -halo:], AXIS, to_right)
    right = jax.lax.ppermute(block[..., :halo], AXIS, to_left)
    return jnp.concatenate([left, block, right], axis=-1)


def site_transform(anom, y_anom, innov, obs_w, taper, one_by_one: bool = False):
    """The LETKF update of a batch of S sites (``letkf_analysis``'s): ``anom (N, S)`` their
    background anomalies; ``y_anom (S, N, W)``, ``innov (S, W)``, ``obs_w (S, W)`` (inverse
    variance, 0 where missing) of the W observations in each site's window; ``taper (W,)``.
    Returns the analysis anomalies ``(N, S)`` (each site's anomalies times ``w_bar + W_a``).

    ``one_by_one``: the S eigendecompositions one after the other (``lax.map``) rather than as
    one batch. jaxlib 0.10's batched CPU LAPACK kernels split a batch over the process's CPU
    thread pool and block until it is done, which deadlocks when several devices of one process
    (``--xla_force_host_platform_device_count``) run theirs at once; the same LAPACK routine
    per matrix, so the same numbers."""
    n = y_anom.shape[1]
    eye = jnp.eye(n, dtype=y_anom.dtype)
    c = y_anom * (taper * obs_w)[:, None, :]                          # (S, N, W)
    m = (n - 1) * eye + c @ jnp.swapaxes(y_anom, 1, 2)                # (S, N, N)
    lam, vec = jax.lax.map(jnp.linalg.eigh, m) if one_by_one else jnp.linalg.eigh(m)
    lam = jnp.maximum(lam, 1e-12)

    def finish(anom_i, c_i, innov_i, lam_i, vec_i):
        p = (vec_i / lam_i) @ vec_i.T
        w_bar = p @ (c_i @ innov_i)
        w_a = (vec_i * jnp.sqrt((n - 1) / lam_i)) @ vec_i.T
        return anom_i @ (w_bar[:, None] + w_a)

    return jax.vmap(finish, in_axes=(1, 0, 0, 0, 0), out_axes=1)(anom, c, innov, lam, vec)


def block_analysis(forecast, hx, y, r_inv, plan: SitePlan):
    """One device's analysis inside ``shard_map``: ``forecast (N, b)`` and predicted observations
    ``hx (N, b)`` of its sites, ``y (b,)`` (NaN: missing or no observation), ``r_inv`` the
    observations' inverse variance. Exchanges the ``(N + 2, h)`` halos (observation anomalies,
    innovations, weights) with both neighbours, analyses the sites ``plan.chunk`` at a time and
    returns the analysis ``(N, b)``."""
    n, b = forecast.shape
    mean = forecast.mean(0)
    anom = forecast - mean
    y_mean = hx.mean(0)
    y_anom = hx - y_mean
    mask = observed(y)
    innov = jnp.where(mask, jnp.where(mask, y, 0.0) - y_mean, 0.0)
    obs_w = jnp.where(mask, r_inv, 0.0).astype(forecast.dtype)
    packed = ring_halo(jnp.concatenate([y_anom, innov[None], obs_w[None]], axis=0), plan.halo,
                       plan.devices)                                  # (N + 2, b + 2h)
    size = plan.chunk
    window = (np.arange(size)[:, None] + plan.halo
              + np.asarray(plan.offsets)[None, :]).astype(np.int32)   # (chunk, 2h + 1)
    taper = jnp.asarray(plan.taper, forecast.dtype)

    def chunk(start):
        part = jax.lax.dynamic_slice_in_dim(packed, start, size + 2 * plan.halo, axis=1)
        local = part[:, window]                                       # (N + 2, chunk, 2h + 1)
        return site_transform(jax.lax.dynamic_slice_in_dim(anom, start, size, axis=1),
                              jnp.swapaxes(local[:n], 0, 1), local[n], local[n + 1], taper,
                              plan.one_by_one)                        # (N, chunk)

    if size == b:
        return mean + chunk(0)
    parts = jax.lax.map(chunk, jnp.arange(0, b, size))               # (b / chunk, N, chunk)
    return mean + jnp.moveaxis(parts, 0, 1).reshape(n, b)


@functools.lru_cache(maxsize=64)
def check_ring(model: StateSpaceModel, localization, name: str = NAME) -> np.ndarray:
    """The observations' sites ``(m,)``, after checking that ``localization`` is the ring of the
    model's d sites (``ring_localization(d, sites)``) and that ``model.observe`` is a point
    sensor whose observation j reads the site the localisation places it at; ValueError
    otherwise (TypeError for something other than a ``Localization``)."""
    if not isinstance(localization, Localization):
        raise TypeError(f"{name}: localization must be a csf_jax.Localization (e.g. "
                        f"csf_jax.ring_localization(d, sites)), got {type(localization).__name__}")
    d, m = model.dim, model.obs_dim
    state = np.asarray(localization.state, np.float64)
    if (localization.period is None or float(localization.period) != float(d)
            or state.shape != (d,) or np.any(state != np.arange(d))):
        raise ValueError(f"{name}: needs the ring of d={d} sites (csf_jax.ring_localization); a "
                         f"line or other positions are not supported")
    placed = np.asarray(localization.obs, np.float64)
    if placed.shape != (m,):
        raise ValueError(f"{name}: the localization has {placed.size} observations; the model "
                         f"has m={m}")
    sites = _model_sensor_sites(model)
    if sites is None:
        raise ValueError(f"{name}: model.observe is not a point sensor (observation j must depend "
                         f"on one site alone: identity, arctan, every k-th site)")
    wrong = np.flatnonzero(placed != sites)
    if wrong.size:
        j = int(wrong[0])
        raise ValueError(f"{name}: observation {j} reads site {int(sites[j])}, but the "
                         f"localization places it at {placed[j]:g} ({wrong.size} of {m} "
                         f"misplaced); give ring_localization(d, sites) with sites[j] the site "
                         f"observation j reads")
    return sites


def _shares_a_cpu_pool(mesh: Mesh) -> bool:
    """Whether several CPU devices of ``mesh`` live in this process (``SitePlan.one_by_one``)."""
    mine = [d for d in mesh.devices.flat if d.process_index == jax.process_index()]
    return len(mine) > 1 and mine[0].platform == "cpu"


def _state_sharding(mesh: Mesh, ndim: int) -> NamedSharding:
    """The sites (last axis) split over ``"sites"``, the other axes whole."""
    return NamedSharding(mesh, P(*([None] * (ndim - 1)), AXIS))


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3))
def _scan(model: StateSpaceModel, plan: SitePlan, mesh: Mesh, return_ensembles: bool,
          inflation, obs, ensemble, key, slot_index, slot_has) -> FilterResult:
    """The filter over ``obs (K, d)`` (observations on their sites, NaN elsewhere) from
    ``ensemble (N, d)``; the same key stream as ``csf_jax.letkf`` (``split(key, K)``)."""
    dtype = ensemble.dtype
    state = _state_sharding(mesh, 2)
    r_inv = 1.0 / jnp.asarray(model.obs_noise.gaussian_std ** 2, dtype)
    analyse = jax.shard_map(functools.partial(block_analysis, r_inv=r_inv, plan=plan), mesh=mesh,
                            in_specs=(P(None, AXIS), P(None, AXIS), P(AXIS)),
                            out_specs=P(None, AXIS))

    def body(ens, xs):
        y, key_k = xs
        forecast, _ = sharded_forecast(model, key_k, ens, inflation, state)
        hx = jax.vmap(model.observe)(forecast).astype(dtype)
        if slot_index is not None:
            hx = jnp.where(slot_has, hx[:, slot_index], 0.0)
        post = analyse(forecast, jax.lax.with_sharding_constraint(hx, state), y)
        return post, (post.mean(0), post.std(0, ddof=1), post if return_ensembles else None)

    keys = jax.random.split(key, obs.shape[0])
    _, (mean, std, ensembles) = jax.lax.scan(body, ensemble, (obs, keys))
    result = mark_nonfinite(FilterResult(mean=mean, std=std, ensembles=ensembles), obs)
    return result._replace(finite=jax.lax.with_sharding_constraint(
        result.finite, NamedSharding(mesh, P())))


def _place(x, sharding: NamedSharding, dtype):
    """``x`` as a global ``jax.Array`` of ``dtype`` with ``sharding``: a host array (the same on
    every process) is cut into the devices' pieces; a global array is resharded if need be."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        if x.dtype == dtype and x.sharding.is_equivalent_to(sharding, x.ndim):
            return x
        return jax.jit(lambda a: a.astype(dtype), out_shardings=sharding)(x)
    host = np.asarray(x).astype(dtype, copy=False)
    return jax.make_array_from_callback(host.shape, sharding, lambda idx: host[idx])


def _is_global(x) -> bool:
    return isinstance(x, jax.Array) and not x.is_fully_addressable


def require_concrete(name: str, *arrays) -> None:
    """TypeError if any of ``arrays`` is a tracer: a sharded filter places its arrays on the mesh
    and runs its own jitted scan, so it is called outside ``jax.jit``/``jax.vmap``."""
    if not _checks.is_concrete(*arrays):
        raise TypeError(f"{name}: takes concrete arrays (it places them on the device mesh "
                        f"itself), not tracers of an outer jax.jit or jax.vmap; call it outside "
                        f"jit")


def _check_arrays(obs, ensemble, model: StateSpaceModel, name: str = NAME) -> None:
    """``check_filter_inputs`` (shapes, dtypes, a finite ensemble, no inf in obs); for global
    arrays spread over processes the shape checks run on their shapes and the value checks as
    global reductions."""
    if not (_is_global(obs) or _is_global(ensemble)):
        _checks.check_filter_inputs(obs, ensemble, model, name=name)
        return
    jax.eval_shape(lambda o, e: _checks.check_filter_inputs(o, e, model, name=name),
                   jax.ShapeDtypeStruct(np.shape(obs), jnp.result_type(obs)),
                   jax.ShapeDtypeStruct(np.shape(ensemble), jnp.result_type(ensemble)))
    if not bool(jax.jit(lambda e: jnp.isfinite(e).all())(ensemble)):
        raise ValueError(f"{name}: ensemble has non-finite value(s)")
    if bool(jax.jit(lambda o: jnp.isinf(o).any())(obs)):
        raise ValueError(f"{name}: obs has infinite value(s) (NaN marks a missing entry; inf is "
                         f"an error)")
    if not _is_global(obs):
        _checks.check_missing_supported(name, obs, model)


def check_mesh_model(model: StateSpaceModel, config, config_type: type, mesh, name: str,
                     one_device: str, adaptive: bool = False) -> None:
    """What the sharded filters filter (module docstring): a time-invariant model with i.i.d.
    additive observation noise, a ``config_type`` config, a mesh with a ``"sites"`` axis;
    ``one_device`` names the filter for the rest; ``adaptive``: whether the filter shards the
    EnKF-N's inflation (``config.adaptive``)."""
    check_model(model, name)
    if not isinstance(config, config_type):
        raise TypeError(f"{name}: config must be a csf_jax.{config_type.__name__}, got "
                        f"{type(config).__name__}")
    if (config.adaptive and not adaptive) or getattr(config, "radii", ()):
        raise ValueError(f"{name}: config.adaptive and config.radii (the EnKF-N's inflation, the "
                         f"radius chosen online: both from the whole step's innovation) are not "
                         f"sharded; leave them off or use {one_device}")
    if model.time_varying:
        raise ValueError(f"{name}: model {model.name!r} is time-varying; it filters "
                         f"time-invariant models (use {one_device})")
    if not is_additive(model) or model.obs_noise.covariance is not None:
        raise ValueError(f"{name}: needs additive observation noise without a covariance (i.i.d. "
                         f"per observation); model {model.name!r} has "
                         f"{model.obs_noise.name!r}")
    if not isinstance(mesh, Mesh) or AXIS not in mesh.axis_names:
        raise ValueError(f"{name}: mesh must be a jax.sharding.Mesh with an axis named {AXIS!r} "
                         f"(csf_jax.site_mesh()), got {mesh!r:.80}")


def concrete_inputs(name: str, method, obs, ensemble, key, inputs) -> tuple:
    """A sharded run's settings and inputs: ``(localization, config, mesh, chunk, obs,
    ensemble)``, the arrays concrete (host or global), the mesh ``site_mesh()`` by default."""
    localization, config, mesh, chunk = method.config
    if inputs is not None:
        raise ValueError(f"{name}: takes no inputs (a time-invariant model)")
    require_concrete(name, obs, ensemble, key)
    mesh = site_mesh() if mesh is None else mesh
    obs, ensemble = (x if isinstance(x, jax.Array) else np.asarray(x) for x in (obs, ensemble))
    return localization, config, mesh, chunk, obs, ensemble


@_checks.renamed_keywords(problem="model")
def sharded_letkf(obs, ensemble, *, model: StateSpaceModel, key, localization: Localization,
                  config: LETKFConfig = LETKFConfig(), mesh: Mesh | None = None,
                  chunk: int = CHUNK, return_ensembles: bool = False,
                  check_finite: bool = True) -> FilterResult:
    """Run the LETKF with the sites split over the devices of ``mesh``'s axis ``"sites"``.

    Args:
      obs: (K, m) observations; NaN marks a missing entry. A host array (the same on every
        process) or a global ``jax.Array``.
      ensemble: (N, d) at time 0; host or global array (placed as ``PartitionSpec(None,
        "sites")``).
      model: the model (static): time-invariant, a point sensor with at most one observation
        per site, i.i.d. additive observation noise.
      key: a ``jax.random.key`` (process noise only), the same on every process.
      localization: ``csf_jax.ring_localization(d, sites)``, sites[j] the site observation j reads.
      config: ``LETKFConfig`` (radius, inflation).
      mesh: a ``jax.sharding.Mesh`` with an axis ``"sites"`` (other axes hold copies); None:
        ``site_mesh()``, all devices of all processes.
      chunk: at most this many sites of a device analysed at once (``SitePlan.chunk``; the same
        numbers whatever it is): it bounds the analysis's working memory.
      return_ensembles: also return the (K, N, d) analysis ensembles.
      check_finite: raise FloatingPointError on a non-finite mean.
    Returns ``FilterResult(mean (K, d), std (K, d), ensembles (K, N, d) | None, finite (K,))``,
    equal to ``csf_jax.letkf``'s up to float round-off; mean, std and ensembles are global arrays
    sharded over the sites (``gather_result`` for numpy copies on every process).
    Raises ValueError for what this version does not filter (module docstring): a localisation
    other than the ring, a sensor that mixes sites, ``d`` not a multiple of the device count, a
    halo wider than a block. Takes concrete arrays (it places them on the mesh), not tracers of an
    outer ``jax.jit``.
    """
    return run(method(localization, config, mesh=mesh, chunk=chunk), obs, ensemble, model=model,
               key=key, return_ensembles=return_ensembles, check_finite=check_finite)


def method(localization: Localization | None = None, config: LETKFConfig = LETKFConfig(), *,
           mesh: Mesh | None = None, chunk: int = CHUNK) -> Method:
    """The sharded LETKF as a ``Method`` for ``csf_jax.run`` (arguments: ``sharded_letkf``); it
    runs its own scan on the mesh, so ``csf_jax.run`` takes concrete arrays for it."""
    localization = require_localization(localization, NAME)
    if not isinstance(config, LETKFConfig):
        raise TypeError(f"{NAME}: config must be a LETKFConfig, got {type(config).__name__}")
    return Method(SHARDED, (localization, config, mesh, chunk))


def _run_method(method, obs, ensemble, *, model, key, inputs=None, return_ensembles=False,
                check_finite=True, progress=None) -> FilterResult:
    localization, config, mesh, chunk, obs, ensemble = concrete_inputs(NAME, method, obs,
                                                                       ensemble, key, inputs)
    check_mesh_model(model, config, LETKFConfig, mesh, NAME, "csf_jax.letkf")
    sites = check_ring(model, localization)
    plan = site_plan(model.dim, float(config.radius), int(mesh.shape[AXIS]), chunk=chunk,
                     one_by_one=_shares_a_cpu_pool(mesh))
    slots = site_slots(sites, model.dim)
    _check_arrays(obs, ensemble, model)
    _checks.check_key(key, NAME)
    dtype = _checks.compute_dtype(jnp.result_type(obs), jnp.result_type(ensemble))
    check_covariances(model, dtype, NAME)
    check_dynamics(model, dtype, None, NAME)
    state, sites_only = _state_sharding(mesh, 2), _state_sharding(mesh, 1)
    slot_index = slot_has = None
    if not slots.identity:                  # observations moved to their sites: (K, m) -> (K, d)
        require_host_obs(NAME, obs)
        host = np.asarray(obs, dtype)
        obs = np.where(slots.has, host[:, slots.index], np.nan).astype(dtype)
        slot_index = _place(slots.index, sites_only, np.int32)
        slot_has = _place(slots.has, sites_only, bool)
    result = _scan(model, plan, mesh, bool(return_ensembles), jnp.asarray(config.inflation),
                   _place(obs, state, dtype), _place(ensemble, state, dtype), key, slot_index,
                   slot_has)
    if check_finite:
        raise_if_diverged(NAME, result)
    return result


def sharded_forecast(model: StateSpaceModel, key, ensemble, inflation, sharding, y=None,
                     adaptive: float = 0.0):
    """The propagated ``ensemble (N, d)`` kept on the sites' ``sharding``, its anomalies scaled by
    ``inflation`` (traced) and, with ``adaptive > 0``, by the EnKF-N's factor for ``y (m,)``
    (``letkf.enkf_n_inflation``, one global computation over the sites). Returns
    ``(forecast (N, d), factor ())`` as ``letkf.inflated_forecast``."""
    dtype = ensemble.dtype
    forecast = jax.lax.with_sharding_constraint(propagate(model, key, ensemble).astype(dtype),
                                                sharding)
    center = forecast.mean(0)
    scale = inflation.astype(dtype)
    factor = jnp.ones((), dtype)
    if adaptive > 0:
        factor = enkf_n_inflation(center + scale * (forecast - center), y, model, adaptive)
        scale = scale * factor
    return jax.lax.with_sharding_constraint(center + scale * (forecast - center),
                                            sharding), factor


def require_host_obs(name: str, obs) -> None:
    """Observations to move onto their sites must be a host array (the identity sensor reads
    global ones in place)."""
    if _is_global(obs):
        raise ValueError(f"{name}: obs spread over processes need the identity sensor "
                         f"(observation j reads site j); give a host array of obs instead")


def raise_if_diverged(name: str, result: FilterResult) -> None:
    """``check_finite`` of a sharded result (its ``finite`` flags gathered to the host)."""
    finite = np.asarray(result.finite)
    _checks.check_result_finite(name, FilterResult(np.where(finite, 0.0, np.nan)[:, None], None))


SHARDED = Kernel(NAME, None, None, label="sharded LETKF", runner=_run_method)


def gather_result(result: FilterResult) -> FilterResult:
    """``result`` with every array as a numpy array holding all of it, on every process
    (``multihost_utils.process_allgather`` for arrays spread over processes)."""
    from jax.experimental import multihost_utils

    if not isinstance(result, FilterResult):
        raise TypeError(f"gather_result: takes the FilterResult of a sharded filter, got "
                        f"{type(result).__name__}")

    def fetch(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return None if x is None else np.asarray(x)

    return FilterResult(*(fetch(x) if not isinstance(x, dict) else x for x in result))
