"""The local CSF in transform form: the LETKF's ensemble space, with a score-based transport.

Each site i is analysed on its own, as in the LETKF (``csf_jax.letkf``): its state is written
``x = x_bar + Z^T w`` with ``Z = (forecast - x_bar) / sqrt(N - 1)`` ``(N, d)``, so the forecast
ensemble's Gaussian is ``w ~ N(0, I_N)``, and the observations in reach enter with their inverse
variances tapered by the Gaspari-Cohn weight of their distance (R-localisation). The local
posterior over ``w`` is sampled by the probability-flow transport of the VE SDE over the noise
levels ``sigma_0 > ... > sigma_L = 0``:

* **Top.** The posterior's mode ``w*`` by ``top_iterations`` Levenberg-Marquardt steps (the
  iterative ensemble Kalman filter's analysis), and the sensor's Jacobian there, ``J (E, N)``,
  with ``P = (I + J^T R~^{-1} J)^{-1}`` from one eigendecomposition ``J^T R~^{-1} J = V L V^T``.
  Each member's coordinates ``sqrt(N - 1) e_n`` are carried up the prior's flow and across to the
  diffused posterior: ``w_n = mu + (P + sigma_0^2)^{1/2} sqrt(N - 1) e_n``.
* **Each level** ``sigma_l -> sigma_{l+1}``: every member's own Tweedie estimate
  ``u_n = E[w_0 | w_sigma = w_n, y]``, the minimiser of
  ``|u|^2 / 2 + |u - w_n|^2 / (2 sigma^2) - log p(y | u)`` by ``iterations`` Gauss-Newton steps
  (the likelihood's gradient at the member's own point, ``J``'s curvature), then the centre
  ``mu_n = P J^T R~^{-1} (y - h(u_n) + J u_n)`` of the Gaussian linearised there, and the exact
  flow of that Gaussian: ``w_n <- mu_n + (P + sigma_{l+1}^2)^{1/2} (P + sigma_l^2)^{-1/2}
  (w_n - mu_n)``.

Every step toward the mode and every Tweedie step is kept within ``trust sqrt(N)`` of the
forecast mean in these coordinates (``LocalTransformConfig.trust``): beyond it the sample
covariance would carry a flat sensor's far observation hundreds of spreads to the neighbouring
sites.

With a linear sensor every ``mu_n`` is the same ``mu`` and the maps telescope to
``mu + P^{1/2} sqrt(N - 1) e_n``: the LETKF's analysis with its symmetric square root, whatever
the levels and iterations, wherever the mode lies within the bound (tested to float64
round-off). With a nonlinear sensor the mode replaces
the LETKF's single linearisation at the forecast mean, and each member is moved by the sensor's
residual at its own point on the way down, so the ensemble keeps the posterior's skew.

**How it is computed.** Every function of ``P`` above is diagonal in ``V``'s basis, so the members
move in the coordinates ``V^T w`` by elementwise steps. When the window has fewer entries E than
members, ``J^T R~^{-1} J`` has rank at most E and its range lies in the E directions the window's
observations read: V is found there from an ``E x E`` eigendecomposition (after a thin QR), and
in the other ``N - E`` directions (``P = I``, nothing observed reads them) each member stays in
the plane of two vectors, carried as four coefficients (``eigen_top``). Else V is the ``N x N``
eigendecomposition's, as the LETKF's. The Levenberg-Marquardt systems ``D + J^T R~^{-1} J``
(D diagonal) are solved through their ``E x E`` form (Woodbury) when ``E < N``. A site's window
is the ``2 h + 1`` sites around it (``h``: ``halo_width``) times the most observations any site
has (``slots``), tapered by distance.

The sensor must be a point sensor (observation j reads one site ``s_j``, as the local CSF needs).
Its values at window values come from ``model.observe`` on full-length states: the sites are cut
into ``classes`` interleaved classes (site i in class ``i mod C``), analysed one after the other,
and the window values of a class fill ``ceil((2 h + 1) / C)`` states per slot and member (sites
``C`` apart have windows ``2 h + 1`` wide, so few overlap), so the sensor's cost stays near one
evaluation per window entry. Within a class the members move in groups (``TransformPlan``), and
the eigendecompositions and solves run ``chunk`` sites at a time: the working memory is a few
arrays of ``N K d / C`` numbers (K = min(E, N) coordinates per member), a small multiple of the
ensemble's ``N d``.
The same functions run a device's block of sites under ``jax.shard_map`` (the halos from the
neighbours by ``ppermute``; ``csf_jax.filters.sharded_transform``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

from csf_jax import _checks
from csf_jax.covariance import gaspari_cohn
from csf_jax.filters.driver import Kernel, Method, StepOutput, run
from csf_jax.filters.letkf import (
    Localization,
    check_adaptive,
    check_localization,
    ensemble_state,
    inflated_forecast,
    require_localization,
)
from csf_jax.filters.result import FilterResult
from csf_jax.sde import marginal_std_host, noise_levels
from csf_jax.ssm import StateSpaceModel, check_model, is_additive, observed

AXIS = "sites"
#: sites analysed at once: a block of at most this many sites is analysed whole; above it the
#: sites are split into classes, the members into groups, and the eigendecompositions and solves
#: run this many sites at a time (``TransformPlan``)
CHUNK = 4096


@dataclasses.dataclass(frozen=True)
class LocalTransformConfig:
    """Settings of the transform-form local CSF.

    Attributes:
      radius: Gaspari-Cohn half-width of the R-localisation, in sites (support ``2 radius``; 1.82x
        DAPPER's ``loc_rad``), as ``LETKFConfig.radius``, in a step whose forecast agrees with
        the observations (``far_radius`` below).
      inflation: multiplicative factor on the forecast anomalies, as ``LETKFConfig.inflation``.
      top_iterations: Gauss-Newton steps to the local posterior's mode (1 is the LETKF's analysis
        linearised at the forecast mean; a saturating sensor such as arctan needs several).
      iterations: Gauss-Newton steps of each member's Tweedie estimate per level, warm-started from
        the level above.
      reverse_steps: L, the noise levels of the transport below the top, geometric from
        ``sigma_t(1)`` to ``sigma_t(t_min)`` (then 0), in units of the forecast's spread.
      t_min, sigma_max: the VE SDE's lowest time and scale (paper: sigma_max 25).
      adaptive: 0 (off), or the EnKF-N hyperprior's certainty, as ``LETKFConfig.adaptive``: each
        step's anomalies are scaled by the factor the step's innovation calls for (1 to 2), on top
        of ``inflation``. The default 2 with ``inflation`` 1 catches the truth again after its
        jumps, where a fixed 1.05 loses it (docs/lorenz96.md).
      trust: the largest norm of a site's ensemble-space point (the mode's and each member's
        Tweedie estimate), in units of ``sqrt(N)``, the typical norm of ``w ~ N(0, I_N)``; a step
        beyond it is shortened onto it. After a jump of the truth an observation far out on a
        flat sensor asks for a move of hundreds of forecast spreads, which the sample covariance
        would carry to the neighbouring sites; bounded, the filter follows the jump over several
        steps as the inflation widens the ensemble. 0: no bound.
      far_radius, far_factor: the half-width of a step whose EnKF-N factor (``adaptive``) exceeds
        ``far_factor``: a forecast that has not caught the truth (a far start, a jump of the
        truth), whose long-range sample correlations carry wrong corrections to distant sites.
        The defaults (radius 15, and 6 beyond a factor of 1.5) keep the larger radius's accuracy
        once the truth is caught and the smaller one's hold while it is not (measured on
        docs/lorenz96.md). ``far_radius`` 0 or at least ``radius``, or ``adaptive`` 0:
        ``radius`` in every step (``switches``). Every step runs one analysis on ``radius``'s
        window; a far step weights it with ``far_radius``'s taper (zero beyond its support), so
        the cost is the same in every step and under ``jax.vmap`` over runs.
    """

    radius: float = 15.0
    inflation: float = 1.0
    top_iterations: int = 5
    iterations: int = 1
    reverse_steps: int = 10
    t_min: float = 1e-3
    sigma_max: float = 25.0
    adaptive: float = 2.0
    trust: float = 6.0
    far_radius: float = 6.0
    far_factor: float = 1.5

    def __post_init__(self):
        _checks.check_fields(self, positive=("radius", "inflation"),
                             nonnegative=("trust", "far_radius"))
        check_adaptive(self)
        if not self.far_factor >= 1.0:
            raise ValueError(f"LocalTransformConfig.far_factor must be >= 1 (an EnKF-N factor), "
                             f"got {self.far_factor}")
        for name in ("top_iterations", "iterations", "reverse_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"LocalTransformConfig.{name} must be an int >= 1, got {value!r}")
        if not 0.0 < self.t_min < 1.0 or not self.sigma_max > 1.0:
            raise ValueError(f"LocalTransformConfig needs 0 < t_min < 1 and sigma_max > 1, got "
                             f"{self.t_min}, {self.sigma_max}")


# --- geometry: where the observations sit, and how the sites are cut ---------------------------


class SiteObs(NamedTuple):
    """The observations of a point sensor, moved onto the sites they read.

    slots: M, the most observations of one site.  identity: observation j reads site j and
    m = d (no re-indexing).  index: ``(M, d)`` int32, the observation in each slot of each site
    (0 where none; by observation order within a site).  has: ``(M, d)`` bool, whether it holds
    one.
    """

    slots: int
    identity: bool
    index: np.ndarray | None
    has: np.ndarray | None


def site_obs(sites, dim: int) -> SiteObs:
    """The ``SiteObs`` of a point sensor whose observation j reads site ``sites[j]`` ``(m,)``."""
    sites = np.asarray(sites, np.int64)
    if sites.size == dim and np.array_equal(sites, np.arange(dim)):
        return SiteObs(1, True, None, None)
    count = np.bincount(sites, minlength=dim)
    slots = max(1, int(count.max()))
    order = np.argsort(sites, kind="stable")
    rank = np.arange(sites.size) - np.searchsorted(sites[order], sites[order], side="left")
    index = np.zeros((slots, dim), np.int32)
    has = np.zeros((slots, dim), bool)
    index[rank, sites[order]] = order
    has[rank, sites[order]] = True
    return SiteObs(slots, False, index, has)


@functools.lru_cache(maxsize=32)
def localization_obs(localization: Localization) -> SiteObs:
    """``site_obs`` of a ring localisation's integer observation positions (cached per
    localisation: the one-device filter's constants)."""
    return site_obs(np.asarray(localization.obs, np.float64).astype(np.int64),
                    len(localization.state))


class TransformPlan(NamedTuple):
    """How the analysis cuts its work (static, hashable); ``transform_plan`` makes it.

    dim: d.  devices: P, blocks of ``block = d / P`` sites, one per device.  left, right: the
    window's reach on each side of a site (h, or less on a ring narrower than ``2 h + 1``).
    taper: ``(left + right + 1,)`` the Gaspari-Cohn weight at offsets ``-left .. right``.
    slots: M, observations per site (``SiteObs.slots``).  classes: C, a divisor of the block:
    site i is analysed with the sites of its class ``i mod C``.  members: members moved at once
    (a divisor of N), or None: all N for an unsplit block, else about N / 4.  chunk: sites per
    eigendecomposition and solve batch (a divisor of ``block / C``).  one_by_one: each site's
    eigendecomposition and solve one after the other (``sharded.site_transform``: several CPU
    devices in one process).
    """

    dim: int
    devices: int
    block: int
    left: int
    right: int
    taper: tuple
    slots: int
    classes: int
    members: int | None
    chunk: int
    one_by_one: bool = False

    @property
    def span(self) -> int:
        """Sites in a window: ``left + right + 1``."""
        return self.left + self.right + 1

    @property
    def entries(self) -> int:
        """E, window entries per site: the span times the slots."""
        return self.span * self.slots

    @property
    def states(self) -> int:
        """Full-length states per slot and member that hold one class's window values."""
        return -(-self.span // self.classes)


def halo_width(radius: float) -> int:
    """The sites on one side of a site whose observations get a positive taper: the largest
    integer offset ``o`` with ``gaspari_cohn(o / radius) > 0`` (0 if none)."""
    reach = np.arange(1, int(np.ceil(2.0 * radius)) + 1)
    inside = reach[gaspari_cohn(reach / radius) > 0]
    return int(inside.max()) if inside.size else 0


def _divisors(n: int) -> list:
    small = [k for k in range(1, int(math.isqrt(n)) + 1) if n % k == 0]
    return sorted(set(small + [n // k for k in small]))


def _largest_divisor(n: int, cap: int) -> int:
    return max(k for k in _divisors(n) if k <= max(1, cap))


def _choose_classes(block: int, span: int, reach: int) -> int:
    """The class count C for a block that is split: a divisor of the block with ``C - 1 + reach``
    within it (one-hop halos), at least ``max(span, 4)`` if one is at most twice that (then each
    class fills one state per slot and member, and a class holds at most a quarter of the sites);
    else the one with the fewest states evaluated, ``C ceil(span / C)``."""
    fits = [c for c in _divisors(block) if c - 1 + reach <= block]
    target = max(span, 4)
    near = [c for c in fits if target <= c <= 2 * target]
    if near:
        return min(near)
    return min(fits, key=lambda c: (c * -(-span // c), -c))


def transform_plan(dim: int, radius: float, *, devices: int = 1, slots: int = 1,
                   chunk: int = CHUNK, classes: int | None = None, members: int | None = None,
                   one_by_one: bool = False, name: str = "local_transform_filter"
                   ) -> TransformPlan:
    """The ``TransformPlan`` of ``dim`` ring sites over ``devices`` blocks at half-width
    ``radius``. A block of at most ``chunk`` sites is analysed whole (one class, all members at
    once); a larger one in ``classes`` (default ``_choose_classes``) and member groups, ``chunk``
    sites per eigendecomposition batch. The results are the same whatever the plan (to float
    round-off). ValueError if ``devices`` does not divide ``dim``, if a window is wider than the
    ring on several devices, or if a halo is wider than a block."""
    for label, value in (("chunk", chunk), ("classes", classes), ("members", members)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer))
                                  or value < 1):
            raise ValueError(f"{name}: {label} must be a positive int, got {value!r}")
    if dim % devices:
        raise ValueError(f"{name}: d={dim} is not a multiple of the {devices} devices of the mesh "
                         f"axis {AXIS!r}; each device takes an equal block of sites")
    block = dim // devices
    h = halo_width(radius)
    if devices > 1 and 2 * h + 1 > dim:
        raise ValueError(f"{name}: the localisation window ({2 * h + 1} sites at radius "
                         f"{radius:g}) is wider than the ring (d={dim}); use a smaller radius")
    left, right = min(h, (dim - 1) // 2), min(h, dim // 2)
    span = left + right + 1
    if max(left, right) > block:
        raise ValueError(f"{name}: the halo ({h} sites on each side at radius {radius:g}) is "
                         f"wider than a device's block ({block} sites = d {dim} / {devices} "
                         f"devices); use fewer devices, a larger d or a smaller radius")
    if classes is None:
        classes = 1 if block <= chunk else _choose_classes(block, span, max(left, right))
    if block % classes or classes - 1 + max(left, right) > block:
        raise ValueError(f"{name}: {classes} classes do not fit a block of {block} sites with a "
                         f"halo of {max(left, right)} (a divisor C of it with C - 1 + halo <= "
                         f"{block}); use fewer devices, a larger d or a smaller radius")
    taper = gaspari_cohn(np.abs(np.arange(-left, right + 1, dtype=np.float64)) / radius)
    return TransformPlan(dim, devices, block, left, right, tuple(float(t) for t in taper),
                         int(slots), int(classes), members, _largest_divisor(block // classes,
                                                                             chunk),
                         bool(one_by_one))


def window_taper(plan: TransformPlan, radius: float) -> np.ndarray:
    """``(span,)`` the Gaspari-Cohn weight at radius ``radius`` of the plan's window offsets
    ``-left .. right``: ``plan.taper`` at the plan's own radius, and zero beyond ``2 radius``
    (a narrower radius analysed on a wider window)."""
    offsets = np.abs(np.arange(-plan.left, plan.right + 1, dtype=np.float64))
    return gaspari_cohn(offsets / radius)


def member_group(plan: TransformPlan, n: int) -> int:
    """B, the members moved at once for an ensemble of ``n``."""
    if plan.members is not None:
        if n % plan.members:
            raise ValueError(f"local_transform_filter: members={plan.members} does not divide the "
                             f"ensemble's N={n}")
        return plan.members
    return n if plan.block <= plan.chunk else _largest_divisor(n, -(-n // 4))


# --- the block: halos, windows and the sensor's states -----------------------------------------


class Ring(NamedTuple):
    """Where the block sits: ``mesh`` None for the whole ring in one array (its halos wrap
    around), else the mesh whose axis ``"sites"`` holds the blocks (halos by ``ppermute``)."""

    mesh: Mesh | None = None
    devices: int = 1


def _extend(x, left: int, right: int, ring: Ring):
    """``x (..., b)`` extended along its last (site) axis to ``(..., left + b + right)`` by the
    sites before and after it on the ring: its own wrapped ends, or the neighbouring devices'."""
    b = x.shape[-1]
    if ring.mesh is None:
        parts = ([x[..., b - left:]] if left else []) + [x] + ([x[..., :right]] if right else [])
    else:
        count = ring.devices
        parts = [x]
        if left:
            parts.insert(0, jax.lax.ppermute(x[..., b - left:], AXIS,
                                             [(i, (i + 1) % count) for i in range(count)]))
        if right:
            parts.append(jax.lax.ppermute(x[..., :right], AXIS,
                                          [(i, (i - 1) % count) for i in range(count)]))
    return jnp.concatenate(parts, axis=-1) if len(parts) > 1 else x


def on_sites(ring: Ring, fn, in_axes: tuple, out_axes):
    """``fn`` on the block: as is for one array; under ``jax.shard_map`` on the mesh otherwise,
    each argument split along its site axis ``in_axes[k]`` (None: the same on every device) and
    each output along ``out_axes`` (a pytree of ints shaped as the outputs)."""
    if ring.mesh is None:
        return fn

    def spec(axis):
        return P() if axis is None else P(*([None] * axis), AXIS)

    outs = jax.tree_util.tree_map(spec, out_axes)
    return jax.shard_map(fn, mesh=ring.mesh, in_specs=tuple(spec(a) for a in in_axes),
                         out_specs=outs)


def _strided(x, start, count: int, stride: int):
    """``x[..., start + k stride]`` for ``k < count`` (``start`` traced)."""
    pad = -x.shape[-1] % stride
    if pad:
        x = jnp.concatenate([x, jnp.zeros(x.shape[:-1] + (pad,), x.dtype)], axis=-1)
    rows = x.reshape(x.shape[:-1] + (x.shape[-1] // stride, stride))
    lead = [0] * (x.ndim - 1)
    out = jax.lax.dynamic_slice(rows, lead + [start // stride, start % stride],
                                x.shape[:-1] + (count, 1))
    return out[..., 0]


def class_window(z, mean, rho_site, yw_site, c, taper, *, plan: TransformPlan, ring: Ring):
    """The windows of class ``c``'s sites of the block. From ``z (N, b)`` (the scaled
    anomalies), ``mean (b,)``, ``rho_site, yw_site (M, b)`` (inverse variance, 0 where none or
    missing; the observation, 0 there) and ``taper (span,)`` (the weight of each offset):
    ``zs (E, N, Q)``, ``xs (E, Q)``, ``rho (E, Q)`` (tapered) and ``yw (E, Q)`` of the
    ``Q = b / C`` sites ``q C + c``; entry ``e = (o + left) M + slot`` of offset ``o``."""
    n, b = z.shape
    m, q = plan.slots, b // plan.classes
    packed = jnp.concatenate([z, mean[None], rho_site, yw_site], axis=0)
    ext = _extend(packed, plan.left, plan.right + plan.classes - 1, ring)
    win = jnp.stack([_strided(ext, c + o, q, plan.classes) for o in range(plan.span)], 0)
    shape = (plan.span, m)
    zs = jnp.broadcast_to(win[:, None, :n], shape + (n, q)).reshape(plan.entries, n, q)
    xs = jnp.broadcast_to(win[:, None, n], shape + (q,)).reshape(plan.entries, q)
    rho = (taper.astype(z.dtype)[:, None, None] * win[:, n + 1:n + 1 + m]).reshape(plan.entries, q)
    return zs, xs, rho, win[:, n + 1 + m:].reshape(plan.entries, q)


def pack_states(values, c, *, plan: TransformPlan, ring: Ring):
    """Window values ``(B, E, Q)`` of class ``c`` placed on full-length states
    ``(M, S, B, b)`` (S = ``plan.states``): state ``(slot, s)`` holds at site ``q C + c + o`` the
    value of entry ``(o, slot)`` of class site q, for the offsets ``o`` of group s (``C``
    consecutive offsets from ``-left + s C``), and 0 at the sites no entry reads."""
    count, _, q = values.shape
    cls, groups, m = plan.classes, plan.states, plan.slots
    b = q * cls
    v = values.reshape(count, plan.span, m, q)
    v = jnp.pad(v, ((0, 0), (0, groups * cls - plan.span), (0, 0), (0, 0)))
    z = jnp.transpose(v.reshape(count, groups, cls, m, q), (3, 1, 0, 4, 2)).reshape(
        m, groups, count, b)                                  # site p = q C + k of the class
    reach = cls - 1 + plan.right
    ext = _extend(z, reach, plan.left, ring)
    return jnp.stack([jax.lax.dynamic_slice_in_dim(ext[:, s], reach - (c - plan.left + s * cls),
                                                   b, axis=-1) for s in range(groups)], axis=1)


def unpack_states(h, c, *, plan: TransformPlan, ring: Ring):
    """The inverse of ``pack_states``: ``h (M, S, B, b)``, values at the states' sites, read back
    at each window entry of class ``c``: ``(B, E, Q)``."""
    m, groups, count, b = h.shape
    cls = plan.classes
    q = b // cls
    ext = _extend(h, plan.left, cls - 1 + plan.right, ring)
    cols = []
    for s in range(groups):
        shift = c - plan.left + s * cls
        part = ext[:, s]
        for k in range(min(cls, plan.span - s * cls)):
            cols.append(_strided(part, plan.left + shift + k, q, cls))   # (M, B, Q)
    win = jnp.stack(cols, 0)                                   # (span, M, B, Q)
    return jnp.transpose(win, (2, 0, 1, 3)).reshape(count, plan.entries, q)


def sites_observer(model: StateSpaceModel, obs: SiteObs, dtype, index=None, has=None,
                   constrain=lambda x: x):
    """``states (M, S, B, d) -> (h, h')``, each ``(M, S, B, d)``: ``model.observe`` of every
    state, read at each site's observation of the state's slot (0 where none), and the sensor's
    derivative there (a point sensor's Jacobian times ones). ``index, has (M, d)``: the slots
    (default ``obs``'s, as constants); ``constrain``: a sharding constraint for the results."""
    def observe(states):
        m, groups, count, d = states.shape
        flat = states.reshape(m, groups * count, d)
        fn = jax.vmap(jax.vmap(model.observe))
        h, dh = jax.jvp(fn, (flat,), (jnp.ones_like(flat),))
        if not obs.identity:
            idx = jnp.asarray(obs.index if index is None else index)
            hold = jnp.asarray(obs.has if has is None else has)
            h = jnp.stack([jnp.where(hold[k], h[k][:, idx[k]], 0.0) for k in range(m)])
            dh = jnp.stack([jnp.where(hold[k], dh[k][:, idx[k]], 0.0) for k in range(m)])
        shape = (m, groups, count, d)
        return (constrain(h.astype(dtype).reshape(shape)),
                constrain(dh.astype(dtype).reshape(shape)))

    return observe


# --- the per-site algebra ----------------------------------------------------------------------


def _lapack(fn, one_by_one: bool):
    """``fn`` over a batch of sites, or site by site (``TransformPlan.one_by_one``)."""
    return (lambda *xs: jax.lax.map(lambda a: fn(*a), xs)) if one_by_one else fn


def _in_chunks(fn, chunk: int, *arrays):
    """``fn`` on ``chunk`` sites at a time (the last axis of every array, a multiple of
    ``chunk``), called with the sites first; its outputs (sites first) returned sites last."""
    q = arrays[0].shape[-1]
    first = tuple(jnp.moveaxis(a, -1, 0) for a in arrays)
    if chunk >= q:
        out = fn(*first)
    else:
        parts = jax.lax.map(lambda xs: fn(*xs),
                            tuple(a.reshape((q // chunk, chunk) + a.shape[1:]) for a in first))
        out = jax.tree_util.tree_map(lambda a: a.reshape((q,) + a.shape[2:]), parts)
    return jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), out)


def lm_trial(u, h, dh, lm, zs, rho, yw, *, plan: TransformPlan):
    """One Levenberg-Marquardt trial point per site: ``u - (H + lm diag(H))^{-1} g`` with
    ``H = I + J^T diag(rho) J``, ``J = h' zs`` and ``g = u - J^T rho (yw - h)``; ``u (N, Q)``,
    ``h, dh, rho, yw (E, Q)``, ``lm (Q,)``, ``zs (E, N, Q)``. With E < N through Woodbury's
    identity on ``D + J^T rho J`` (D diagonal), an ``E x E`` system; else the ``N x N`` one."""
    n = u.shape[0]
    solve = _lapack(lambda a, r: jnp.linalg.solve(a, r[..., None])[..., 0], plan.one_by_one)

    def part(u, h, dh, lm, zs, rho, yw):                      # sites first
        jac = dh[..., None] * zs
        grad = u - jnp.einsum("qek,qe->qk", jac, rho * (yw - h))
        if plan.entries < n:
            colsq = jnp.einsum("qek,qe,qek->qk", jac, rho, jac)
            dinv = 1.0 / (1.0 + lm[:, None] * (1.0 + colsq))
            t = dinv * grad
            eye = jnp.eye(plan.entries, dtype=u.dtype)
            small = eye + rho[..., None] * jnp.einsum("qek,qk,qfk->qef", jac, dinv, jac)
            x = solve(small, rho * jnp.einsum("qek,qk->qe", jac, t))
            return u - (t - dinv * jnp.einsum("qek,qe->qk", jac, x))
        eye = jnp.eye(n, dtype=u.dtype)
        hess = eye + jnp.einsum("qek,qe,qel->qkl", jac, rho, jac)
        damped = hess + (lm[:, None, None] * eye) * jnp.diagonal(hess, axis1=1, axis2=2)[:, None]
        return u - solve(damped, grad)

    return _in_chunks(part, plan.chunk, u, h, dh, lm, zs, rho, yw)


class Top(NamedTuple):
    """A class's sites at the top of the transport, in the coordinates of K directions ``V``
    (sites last): all N eigenvectors of ``J^T rho J`` when ``E >= N``, else the E directions of
    the window's reach (``eigen_top``), the other ``N - E`` kept as a null block.

    lam: ``(K, Q)`` eigenvalues of ``J^T rho J`` on them.  mode: ``(K, Q)`` the mode ``V^T u``.
    top: ``(N, K, Q)`` each member's top point.  zsr: ``(E, K, Q)`` the window's anomalies
    ``zs V``.  null: None, or the null block's ``(|a|^2 (Q,), <a, g_n> (N, Q), |g_n|^2 (N, Q),
    a . z (Q,), g_n . z (N, Q))`` with ``a`` the mode's and ``g_n`` member n's unit vector's
    projections on the null space, ``z`` the site's anomalies.
    """

    lam: jax.Array
    mode: jax.Array
    top: jax.Array
    zsr: jax.Array
    null: tuple | None


def eigen_top(u, dh, zs, rho, sigma0, *, plan: TransformPlan) -> Top:
    """The top of the transport at the mode ``u (N, Q)`` with ``h' (E, Q)`` (``zs (E, N, Q)``,
    ``rho (E, Q)``): the eigendecomposition of ``J^T rho J``, ``J = h' zs``, and the members'
    top points ``V^T u + sqrt(N - 1) (P + sigma0^2)^{1/2} V^T e_n`` (``Top``).

    With ``E < N`` the rank of ``J^T rho J`` is at most E, and its range lies in that of
    ``(sqrt(rho) zs)^T``: with that range's orthonormal basis ``Q_E (N, E)`` (a thin QR) the
    eigenvectors are ``Q_E U`` for the eigenvectors U of the ``E x E`` matrix
    ``(B Q_E)^T (B Q_E)``, ``B = sqrt(rho) J``, and the ``N - E`` others span the null space, where
    ``P = I``. Every observed window entry reads nothing there (``zs Q_perp = 0``), so there each
    member moves in the plane of its two starting vectors, the mode's projection ``a`` and
    ``g_n``, its unit vector's (the level step keeps four coefficients per member)."""
    n = u.shape[0]
    width = plan.entries
    offset = plan.left * plan.slots                      # the entry of offset 0, slot 0: the site
    eigh = _lapack(jnp.linalg.eigh, plan.one_by_one)
    qr = _lapack(jnp.linalg.qr, plan.one_by_one)

    def part(u, dh, zs, rho):                                 # sites first
        jac = dh[..., None] * zs                              # (Q, E, N)
        root = jnp.sqrt(rho)[..., None]
        if width < n:
            # the eigendecomposition's input is made from the QR's Q, so it waits for it:
            # jaxlib's batched CPU LAPACK kernels block on the shared thread pool, and two of
            # them running at once can deadlock it
            basis, _ = qr(jnp.swapaxes(root * zs, 1, 2))       # (Q, N, E)
            small = (root * jac) @ basis                       # (Q, E, E): B Q_E
            lam, rot = eigh(jnp.swapaxes(small, 1, 2) @ small)
            vec = basis @ rot                                 # (Q, N, E)
            site = zs[:, offset]                              # (Q, N)
            qu = jnp.einsum("qnk,qn->qk", basis, u)
            qz = jnp.einsum("qnk,qn->qk", basis, site)
            a = u - jnp.einsum("qnk,qk->qn", basis, qu)       # the mode's null part, P u
            null = (jnp.sum(u * u, 1) - jnp.sum(qu * qu, 1), a,
                    1.0 - jnp.sum(basis * basis, 2), jnp.sum(a * site, 1),
                    site - jnp.einsum("qnk,qk->qn", basis, qz))
        else:
            lam, vec = eigh(jnp.einsum("qek,qe,qel->qkl", jac, rho, jac))
            null = None
        lam = jnp.maximum(lam, 0.0)
        top = jnp.sqrt(jnp.asarray(n - 1, u.dtype)) * jnp.sqrt(1.0 / (1.0 + lam) + sigma0 ** 2)
        ur = jnp.einsum("qkl,qk->ql", vec, u)
        return Top(lam, ur, ur[:, None, :] + top[:, None, :] * vec,
                   jnp.einsum("qek,qkl->qel", zs, vec), null)

    return _in_chunks(part, plan.chunk, u, dh, zs, rho)


def _total(x, axis: int):
    """``x.sum(axis)`` for a short axis that is not the last, as a chain of elementwise adds:
    XLA's CPU reduction over a leading axis of a site-last array runs much slower than the same
    adds, which XLA fuses into one loop."""
    return functools.reduce(lambda a, b: a + b, [jax.lax.index_in_dim(x, k, axis, False)
                                                  for k in range(x.shape[axis])])


def _within(u, axis: int, bound: float):
    """``u`` shortened, where its norm over ``axis`` exceeds ``bound``, onto that norm (0: no
    bound)."""
    if bound == 0:
        return u
    norm = jnp.sqrt(_total(u * u, axis))
    return u * jnp.expand_dims(jnp.minimum(1.0, bound / jnp.maximum(norm, bound * 1e-30)), axis)


def _levels(config: LocalTransformConfig):
    """``(L + 1,)`` float64 noise levels: geometric from ``sigma_t(1)`` to ``sigma_t(t_min)``,
    then 0."""
    return np.asarray(noise_levels(config.reverse_steps, marginal_std_host(1.0, config.sigma_max),
                                   marginal_std_host(config.t_min, config.sigma_max)), np.float64)


def analysis(forecast, y_sites, prec_sites, observe, plan: TransformPlan,
             config: LocalTransformConfig, ring: Ring = Ring(), taper=None):
    """The transform-form analysis of ``forecast (N, d)`` (module docstring).

    y_sites: ``(M, d)`` each site's observations (NaN: none or missing).  prec_sites: ``(M, d)``
    their inverse variances.  observe: ``sites_observer``'s function.  plan, ring: how the work is
    cut and where the block sits.  taper: ``(span,)`` the weight of each window offset, traced
    (default ``plan.taper``; ``step_taper``). Arrays of a class keep their Q sites last, so the
    per-site steps are elementwise over them. Returns the posterior ensemble ``(N, d)``.
    """
    n, d = forecast.shape
    dtype = forecast.dtype
    group = member_group(plan, n)
    levels = _levels(config)
    bound = float(config.trust) * math.sqrt(n)      # the norm of the trusted ensemble-space points
    mean = forecast.mean(0)
    z = (forecast - mean) / jnp.sqrt(jnp.asarray(n - 1, dtype))                # (N, d)
    mask = observed(y_sites)
    rho_site = jnp.where(mask, prec_sites, 0.0).astype(dtype)
    yw_site = jnp.where(mask, y_sites, 0.0).astype(dtype)
    taper = jnp.asarray(plan.taper if taper is None else taper, dtype)
    window = on_sites(ring, functools.partial(class_window, plan=plan, ring=ring),
                      (1, 0, 1, 1, None, None), (2, 1, 1, 1))
    pack = on_sites(ring, functools.partial(pack_states, plan=plan, ring=ring), (2, None), 3)
    unpack = on_sites(ring, functools.partial(unpack_states, plan=plan, ring=ring), (3, None), 2)
    trial_of = on_sites(ring, functools.partial(lm_trial, plan=plan), (1, 1, 1, 0, 2, 1, 1), 1)
    reduced = plan.entries < n
    top_of = on_sites(ring, functools.partial(eigen_top, plan=plan), (1, 1, 2, 1, None),
                      Top(1, 1, 2, 2, (0, 1, 1, 0, 1) if reduced else None))
    offset = plan.left * plan.slots                     # the entry of offset 0, slot 0: the site

    def sensor(values, c):
        """``h, h'`` at window values ``(K, E, Q)`` of class c; each ``(K, E, Q)``."""
        count = values.shape[0]
        h, dh = observe(pack(values, c))
        both = unpack(jnp.concatenate([h, dh], axis=2), c)
        return both[:count], both[count:]

    def one_class(c):
        zs, xs, rho, yw = window(z, mean, rho_site, yw_site, c, taper)
        q = zs.shape[-1]

        def cost(u, h):
            """The local posterior's negative log-density (up to a constant): ``u (K, N, Q)``,
            ``h (K, E, Q)`` -> ``(K, Q)``."""
            return 0.5 * _total(u ** 2, 1) + 0.5 * _total(rho * (yw - h) ** 2, 1)

        def mode_step(carry, _):
            """Levenberg-Marquardt: a Gauss-Newton step damped by ``lm diag(H)``; kept where it
            lowers the site's cost, else the damping grows fourfold (a linear sensor's first
            step is exact and final)."""
            u, h, dh, c_u, lm = carry
            trial = _within(trial_of(u, h, dh, lm, zs, rho, yw), 0, bound)
            h_t, dh_t = sensor((xs + jnp.einsum("enq,nq->eq", zs, trial))[None], c)
            c_t = cost(trial[None], h_t)[0]
            better = c_t < c_u
            return (jnp.where(better, trial, u), jnp.where(better, h_t[0], h),
                    jnp.where(better, dh_t[0], dh), jnp.where(better, c_t, c_u),
                    jnp.where(better, lm / 4.0, jnp.maximum(4.0 * lm, 0.25))), None

        u = jnp.zeros((n, q), dtype)
        h, dh = sensor(xs[None], c)
        init = (u, h[0], dh[0], cost(u[None], h)[0], jnp.zeros((q,), dtype))
        (u, h, dh, _, _), _ = jax.lax.scan(mode_step, init, None, length=config.top_iterations)
        top = top_of(u, dh, zs, rho, jnp.asarray(levels[0], dtype))
        lam, zsr = top.lam, top.zsr
        p_eig = 1.0 / (1.0 + lam)                                          # (K, Q)

        def quad(x, y, gram):
            """``|x a + y g_n|^2`` from the null block's Gram entries."""
            g_aa, g_ag, g_gg = gram
            return x * x * g_aa + 2.0 * x * y * g_ag + y * y * g_gg

        def level(carry, sig):
            """One level for B members: ``w, uw (B, K, Q)``, ``h, h' (B, E, Q)`` at ``uw``, and
            the null block's coefficients ``(B, 4, Q)`` (``w = alpha a + beta g``,
            ``uw = gamma a + delta g`` there) with its Gram entries."""
            w, uw, h_b, dh_b, nul, gram = carry
            sigma, sigma_next = sig
            s = 1.0 / sigma ** 2
            inv_den = 1.0 / (1.0 + s + lam)
            d0 = uw - w
            c_b = 0.5 * _total(uw * uw + s * d0 * d0, 1) + 0.5 * _total(rho * (yw - h_b) ** 2, 1)
            if nul is not None:
                al, be, ga, de = (nul[:, k] for k in range(4))
                kappa = s / (1.0 + s)
                c_b = c_b + 0.5 * (quad(ga, de, gram) + s * quad(ga - al, de - be, gram))
                c_null = 0.5 * quad(al, be, gram) * (kappa ** 2 + s * (1.0 - kappa) ** 2)
            for _ in range(config.iterations):
                resid = jnp.einsum("ekq,beq->bkq", zsr, dh_b * rho * (yw - h_b))  # (B, K, Q)
                trial = _within(uw - (uw + s * d0 - resid) * inv_den, 1, bound)
                h_t, dh_t = sensor(xs + jnp.einsum("ekq,bkq->beq", zsr, trial), c)
                d1 = trial - w
                c_t = (0.5 * _total(trial * trial + s * d1 * d1, 1)
                       + 0.5 * _total(rho * (yw - h_t) ** 2, 1))
                if nul is not None:
                    c_t = c_t + c_null
                better = c_t < c_b
                keep = better[:, None]
                uw, h_b, dh_b = (jnp.where(keep, trial, uw), jnp.where(keep, h_t, h_b),
                                 jnp.where(keep, dh_t, dh_b))
                if nul is not None:
                    ga, de = jnp.where(better, kappa * al, ga), jnp.where(better, kappa * be, de)
                c_b = jnp.minimum(c_t, c_b)
                d0 = uw - w
            mu_b = uw + p_eig * s * d0
            ratio = jnp.sqrt((p_eig + sigma_next ** 2) / (p_eig + sigma ** 2))
            if nul is not None:
                m1, m2 = ga + s * (ga - al), de + s * (de - be)
                r0 = jnp.sqrt((1.0 + sigma_next ** 2) / (1.0 + sigma ** 2))
                nul = jnp.stack([m1 + r0 * (al - m1), m2 + r0 * (be - m2), ga, de], 1)
            return (mu_b + ratio * (w - mu_b), uw, h_b, dh_b, nul, gram), None

        sig = (jnp.asarray(levels[:-1], dtype), jnp.asarray(levels[1:], dtype))
        zr = zsr[offset]                                                   # (K, Q): V^T z_i
        tau = jnp.sqrt(jnp.asarray(n - 1, dtype) * (1.0 + jnp.asarray(levels[0], dtype) ** 2))

        def one_group(g):
            def members(x):
                return jax.lax.dynamic_slice_in_dim(x, g * group, group, axis=0)

            w = members(top.top)                                           # (B, K, Q)
            shape = (group, plan.entries, q)
            nul = gram = None
            if top.null is not None:
                g_aa, g_ag, g_gg, z_a, z_g = top.null
                gram = (g_aa, members(g_ag), members(g_gg))
                one, zero = jnp.ones((group, q), dtype), jnp.zeros((group, q), dtype)
                nul = jnp.stack([one, tau * one, one, zero], 1)            # (B, 4, Q)
            carry = (w, jnp.broadcast_to(top.mode, w.shape), jnp.broadcast_to(h, shape),
                     jnp.broadcast_to(dh, shape), nul, gram)
            (w, _, _, _, nul, _), _ = jax.lax.scan(level, carry, sig)
            out = _total(w * zr, 1)                                        # (B, Q)
            if nul is not None:
                out = out + nul[:, 0] * z_a + nul[:, 1] * members(z_g)
            return out

        if group == n:
            return one_group(0)
        return jax.lax.map(one_group, jnp.arange(n // group)).reshape(n, q)

    if plan.classes == 1:
        local = one_class(jnp.asarray(0))                                  # (N, d)
    else:
        parts = jax.lax.map(one_class, jnp.arange(plan.classes))           # (C, N, d / C)
        local = on_sites(ring, lambda x: jnp.transpose(x, (1, 2, 0)).reshape(n, -1), (2,),
                         1)(parts)
    return mean + local


def transform_analysis(forecast, y, model: StateSpaceModel, localization: Localization,
                       config: LocalTransformConfig, *, chunk: int = CHUNK,
                       plan: TransformPlan | None = None, taper=None):
    """The one-device analysis of ``forecast (N, d)`` on ``y (m,)`` (NaN: missing) for a point
    sensor at ``localization.obs`` (``ring_localization``). ``plan``: how to cut the work
    (default ``transform_plan(d, radius, chunk=chunk)``); ``taper``: as ``analysis``'s. Returns
    the posterior ``(N, d)``."""
    obs = localization_obs(localization)
    d = forecast.shape[1]
    if plan is None:
        plan = transform_plan(d, float(config.radius), slots=obs.slots, chunk=chunk)
    dtype = forecast.dtype
    prec = jnp.broadcast_to(jnp.asarray(1.0 / np.asarray(model.obs_noise.gaussian_std) ** 2,
                                        dtype), y.shape)
    if obs.identity:
        y_sites, prec_sites = y[None], prec[None]
    else:
        has, index = jnp.asarray(obs.has), jnp.asarray(obs.index)
        y_sites = jnp.where(has, y[index], jnp.nan)
        prec_sites = jnp.where(has, prec[index], 0.0)
    return analysis(forecast, y_sites.astype(dtype), prec_sites, sites_observer(model, obs, dtype),
                    plan, config, taper=taper)


# --- the filter --------------------------------------------------------------------------------


class TransformStatic(NamedTuple):
    """The static settings for the driver: the config, the geometry and ``chunk``."""

    config: LocalTransformConfig
    localization: Localization
    chunk: int = CHUNK


def switches(config: LocalTransformConfig) -> bool:
    """Whether ``config`` analyses some steps at ``far_radius`` (``LocalTransformConfig``)."""
    return config.adaptive > 0 and 0 < config.far_radius < config.radius


def step_taper(plan: TransformPlan, config: LocalTransformConfig, factor):
    """The step's ``(span,)`` window taper and ``(far, radius)`` (scalars): ``far_radius``'s
    taper on ``plan``'s window where the EnKF-N ``factor`` exceeds ``far_factor`` (and
    ``switches``), else ``plan.taper``. One analysis on one window either way: a ``lax.cond``
    between two windows would run both under ``jax.vmap``."""
    wide = jnp.asarray(plan.taper)
    if not switches(config):
        return wide, None
    far = factor > config.far_factor
    taper = jnp.where(far, jnp.asarray(window_taper(plan, config.far_radius)), wide)
    return taper, jnp.where(far, config.far_radius, config.radius)


def _step(model: StateSpaceModel, static: TransformStatic, inflation, ensemble, y, key, time):
    """Forecast, inflate and analyse every site of ``ensemble (N, d)`` on ``y (m,)``; where
    ``switches``, at ``far_radius`` in a step whose EnKF-N factor exceeds ``far_factor``
    (``info["radius"]``: the step's radius)."""
    config = static.config
    forecast, factor = inflated_forecast(model, key, ensemble, inflation, y, config.adaptive)
    plan = transform_plan(model.dim, float(config.radius),
                          slots=localization_obs(static.localization).slots, chunk=static.chunk)
    taper, radius = step_taper(plan, config, factor)
    post = transform_analysis(forecast, y, model, static.localization, config,
                              plan=plan, taper=taper)
    if radius is None:
        return post, StepOutput(post.mean(0), post.std(0, ddof=1), post)
    info = {"radius": radius.astype(forecast.dtype)}
    return post, StepOutput(post.mean(0), post.std(0, ddof=1), post, info)


def _check(model: StateSpaceModel, static: TransformStatic) -> None:
    if not is_additive(model) or model.time_varying:
        raise ValueError("local_transform_filter: needs a time-invariant point sensor with "
                         "additive noise (not a Likelihood, not time_varying)")
    if model.obs_noise.covariance is not None:
        raise ValueError("local_transform_filter: needs uncorrelated observation noise "
                         "(R-localisation divides by each observation's variance)")


LOCAL_TRANSFORM = Kernel("local_transform_filter", ensemble_state, _step, _check,
                         label="local CSF (transform)")


@_checks.renamed_keywords(problem="model")
def local_transform_filter(obs, ensemble, *, model: StateSpaceModel, key,
                           localization: Localization | None = None,
                           config: LocalTransformConfig = LocalTransformConfig(),
                           chunk: int = CHUNK, return_ensembles: bool = False,
                           check_finite: bool = True, progress=None) -> FilterResult:
    """Filter ``obs`` with the transform-form local CSF (module docstring).

    Args:
      obs: (K, m) observations; NaN marks a missing entry.  ensemble: (N, d) at time 0.
      model: the model (static); its sensor must be a point sensor at ``localization.obs``,
        with independent noise (a non-Gaussian noise enters through its Gaussian stand-in
        ``gaussian_std``, as in the LETKF).
      key: a ``jax.random.key`` (process noise only: the analysis is deterministic).
      localization: ``csf_jax.ring_localization(d, obs_sites)``.
      config: ``LocalTransformConfig``; its inflation is traced (a sweep compiles once).
      chunk: up to this many sites the analysis runs on all sites at once; above, it works
        through them in classes, member groups and batches of ``chunk`` sites
        (``TransformPlan``), which bounds its memory to a small multiple of the ensemble. The
        results are the same to float round-off.
      return_ensembles: also return the (K, N, d) ensembles.
      check_finite: raise FloatingPointError on a non-finite mean (concrete runs only).
      progress: optional host callback ``k -> None`` at every step.
    Returns ``FilterResult(mean (K, d), std (K, d), ensembles | None, finite (K,))``; jit-able
    (bind the keywords statically) and vmap-able over ``(obs, ensemble, key)``.
    """
    return run(method(localization, config, chunk=chunk), obs, ensemble, model=model, key=key,
               return_ensembles=return_ensembles, check_finite=check_finite, progress=progress)


def method(localization: Localization | None = None,
           config: LocalTransformConfig = LocalTransformConfig(), *,
           chunk: int = CHUNK) -> Method:
    """The transform-form local CSF as a ``Method`` for ``csf_jax.run``.

    Args:
      localization: ``csf_jax.ring_localization(d, obs_sites)``.
      config: ``LocalTransformConfig``; its inflation is traced, the rest static.
      chunk: as ``local_transform_filter``'s.
    """
    localization = require_localization(localization, "local_transform_filter")
    if not isinstance(config, LocalTransformConfig):
        raise TypeError(f"local_transform_filter: config must be a LocalTransformConfig, got "
                        f"{type(config).__name__}")
    if isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or chunk < 1:
        raise ValueError(f"local_transform_filter: chunk must be a positive int, got {chunk!r}")
    static = TransformStatic(dataclasses.replace(config, inflation=1.0), localization, int(chunk))
    return Method(LOCAL_TRANSFORM._replace(bind=_bind), static, jnp.asarray(config.inflation))


def _bind(model, static: TransformStatic, params, state0):
    check_model(model, "local_transform_filter")
    _check(model, static)
    check_localization(model, static.localization, "local_transform_filter", points=True)
    return model, static, params, state0
